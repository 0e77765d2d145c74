"""``meniscope publish-frames``: replay a recording to a ZeroMQ socket, as a remote camera would stream it."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "publish-frames",
        help="replay a recording to a ZeroMQ PUB socket (docs/zmq-frames.md)",
        description="Replay a recording (.cine or .avi) to a ZeroMQ socket in the frame format of "
        "docs/zmq-frames.md, starting when the first subscriber connects; `meniscope serve --source "
        "zmq+tcp://HOST:PORT` receives it. Subscribers that lag lose frames rather than slow the replay.",
    )
    p.add_argument("recording", type=Path, metavar="REC", help="recording to replay (.cine or .avi)")
    p.add_argument(
        "--bind",
        default="tcp://127.0.0.1:5557",
        help="ZeroMQ endpoint to publish on (default tcp://127.0.0.1:5557: this machine only)",
    )
    p.add_argument(
        "--speed",
        default="1.0",
        help="times the recorded frame rate, e.g. 0.1 for slow motion; 0 or max: as fast as possible",
    )
    p.add_argument("--loop", action="store_true", help="start again at the end (frame indices keep increasing)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from service.sources import FrameSender, open_source  # OpenCV and ZeroMQ load only when the verb runs

    # open once to report a bad file or option before waiting; reopening restarts the replay clock
    source = open_source(str(args.recording), speed=args.speed, loop=args.loop)
    fmt = source.format
    source.close()
    with FrameSender(args.bind, fmt) as sender:
        print(f"{args.recording}: waiting for a subscriber on {args.bind}", file=sys.stderr)
        while not sender.wait_for_subscriber(1.0):
            pass
        with source:
            while (batch := source.read(256)) is not None:
                sender.send(batch)
        print(
            f"{args.recording}: published {source.stats.frames} frames in {sender.sequence} messages", file=sys.stderr
        )
    return 0
