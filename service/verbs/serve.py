"""``meniscope serve``: the monitoring service (REST, WebSocket, dashboard, Prometheus, ZeroMQ; docs/service.md)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from service.server.settings import ServiceSettings


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "serve",
        help="the monitoring service: live analysis of a camera or recording, dashboard and APIs",
        description="Run the live pipeline on a frame source and publish every window's fit over REST, "
        "WebSocket, Prometheus and ZeroMQ, with a dashboard at http://HOST:PORT/. With no source it replays "
        "a recording made by our simulator, in a loop. Settings (docs/service.md): defaults, then --config, then "
        "MENISCOPE_* environment variables, then these options.",
    )
    p.add_argument(
        "--source",
        help="source URI or recording path (default: the demo recording; URI schemes in "
        "docs/service.md); a recording named here, as a path or a file:// URI, makes its "
        "folder the recordings folder, unless recordings_dir is set",
    )
    p.add_argument("--config", type=Path, help="settings file, TOML or JSON")
    p.add_argument("--host", help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, help="HTTP port (default 8000)")
    p.add_argument(
        "--refine",
        action="store_const",
        const=True,
        help="also refine windows by synthesis on a lane of their own (as analyze --refine; tens of seconds a "
        "window: the newest each time, published as an update of the same window id; setting refine)",
    )
    p.set_defaults(func=run, own_signals=True)  # uvicorn's shutdown and the pipeline process' stop


def serve_settings(args: argparse.Namespace) -> ServiceSettings:
    """The settings ``args`` ask for, loaded and validated once with the options on top (an option mends a
    bad value of the config file); a recording named by ``--source`` makes its folder the recordings
    folder unless ``recordings_dir`` is set (the person at the console may name any recording)."""
    from service.server.settings import load_settings, recording_folder

    folder = None if args.source is None else recording_folder(args.source)
    return load_settings(
        args.config, {"recordings_dir": folder}, source=args.source, host=args.host, port=args.port, refine=args.refine
    )


def run(args: argparse.Namespace) -> int:
    import uvicorn  # the web stack loads only when the verb runs

    from service.server.app import create_app

    logging.basicConfig(level=logging.WARNING, format="meniscope serve: %(levelname)s: %(message)s")
    settings = serve_settings(args)
    if not settings.loopback and settings.token is None:
        print(
            f"meniscope serve: bound to {settings.host} without a token: settings cannot be changed over HTTP "
            "(set MENISCOPE_TOKEN)",
            file=sys.stderr,
        )
    print(
        f"meniscope serve: dashboard on http://{settings.host}:{settings.port}/, window results on ZeroMQ "
        f"{settings.zmq_publish or '(off)'}; source {settings.source or 'the demo recording'}",
        file=sys.stderr,
    )
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level="warning")
    return 0
