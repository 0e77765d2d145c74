"""``meniscope serve``: the monitoring service (REST, WebSocket, dashboard, Prometheus, ZeroMQ; docs/service.md)."""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "serve",
        help="the monitoring service: live analysis of a camera or recording, dashboard and APIs",
        description="Run the live pipeline on a frame source and publish every window's fit over REST, "
        "WebSocket, Prometheus and ZeroMQ, with a dashboard at http://HOST:PORT/. With no source it replays "
        "a recording made by our simulator, in a loop. Settings (docs/service.md): defaults, then --config, then "
        "MENISCOPE_* environment variables, then these options.",
    )
    p.add_argument("--source", help="source URI or recording path (default: the demo recording; URI schemes in "
                                    "docs/service.md); a recording named here makes its folder the recordings "
                                    "folder, unless recordings_dir is set")
    p.add_argument("--config", type=Path, help="settings file, TOML or JSON")
    p.add_argument("--host", help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, help="HTTP port (default 8000)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import uvicorn  # the web stack loads only when the verb runs

    from service.server.app import create_app
    from service.settings import load_settings

    logging.basicConfig(level=logging.WARNING, format="meniscope serve: %(levelname)s: %(message)s")
    settings = load_settings(args.config, host=args.host, port=args.port)
    if args.source is not None:
        folder = settings.recordings_dir
        if folder is None and "://" not in args.source:  # the person at the console may name any recording
            folder = Path(args.source).expanduser().resolve().parent
        settings = load_settings(args.config, source=args.source, host=args.host, port=args.port,
                                 recordings_dir=folder)
    if not settings.loopback and settings.token is None:
        print(f"meniscope serve: bound to {settings.host} without a token: settings cannot be changed over HTTP "
              "(set MENISCOPE_TOKEN)", file=sys.stderr)
    print(f"meniscope serve: dashboard on http://{settings.host}:{settings.port}/, window results on ZeroMQ "
          f"{settings.zmq_publish or '(off)'}; source {settings.source or 'the demo recording'}", file=sys.stderr)
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level="warning")
    return 0
