"""Verbs ``info`` and ``frames``: what a recording's header says, and its frames as stored, to .npy."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from service.errors import MeniscopeError, require_folder_of

#: Frames copied per step of ``frames``: bounded by bytes, so big frames do not need big memory.
CHUNK_BYTES = 64 * 2**20


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``info`` and ``frames`` to the ``meniscope`` command."""
    info = subparsers.add_parser(
        "info",
        help="print a recording's header as one JSON object",
        description="One JSON object on stdout: frames, fps, width, height, bit depth, and what else the "
        "file header says (timestamps, trigger frame, camera).",
    )
    info.add_argument("recording", metavar="REC", type=Path, help="a .cine or .avi file")
    info.set_defaults(func=run_info)

    frames = subparsers.add_parser(
        "frames",
        help="save frames exactly as stored to a .npy file",
        description="Frames with pixel values exactly as stored (uint8 or uint16, no scaling), rows in "
        "display order (top row first), shape (N, height, width).",
    )
    frames.add_argument("recording", metavar="REC", type=Path, help="a .cine or .avi file")
    frames.add_argument("--start", metavar="I", type=int, default=0, help="first frame (default 0)")
    frames.add_argument(
        "--count", metavar="N", type=int, default=None, help="number of frames (default: from --start to the end)"
    )
    frames.add_argument("--out", metavar="FRAMES.npy", type=Path, required=True, help="the .npy file to write")
    frames.set_defaults(func=run_frames)


def run_info(args: argparse.Namespace) -> int:
    """Print the recording's :meth:`~service.recordings.Recording.info` as JSON."""
    from service.recordings import open_recording

    with open_recording(args.recording) as recording:
        print(json.dumps(recording.info(), indent=2, allow_nan=False))
    return 0


def run_frames(args: argparse.Namespace) -> int:
    """Copy frames ``--start`` .. ``--start + --count - 1`` into a .npy file, a chunk at a time."""
    import numpy as np
    from tqdm import tqdm

    from service.recordings import open_recording

    out: Path = args.out
    require_folder_of(out)
    with open_recording(args.recording) as recording:
        count = len(recording) - args.start if args.count is None else args.count
        frames = recording.frame_range(args.start, count)
        shape = (len(frames), recording.height, recording.width)
        step = max(1, CHUNK_BYTES // (recording.height * recording.width * recording.dtype.itemsize))
        try:
            array = np.lib.format.open_memmap(out, mode="w+", dtype=recording.dtype, shape=shape)
            with tqdm(total=len(frames), unit="frame", desc=f"frames {out.name}", disable=None) as bar:
                for first in frames[::step]:
                    n = min(step, frames.stop - first)
                    array[first - frames.start : first - frames.start + n] = recording.read(first, n)
                    bar.update(n)
            array.flush()
        except OSError as exc:
            out.unlink(missing_ok=True)
            raise MeniscopeError(out, f"cannot write: {exc.strerror or exc}") from None
        except MeniscopeError:
            out.unlink(missing_ok=True)
            raise
    return 0
