"""The demo that ``meniscope serve`` runs with no source: a recording made by our simulator, in a loop.

The package ships it small (``service/demo/demo.avi``: 4 windows, 760 frames, 8-bit FFV1, written by
``meniscope simulate --out demo.avi --windows 4 --seed 1``, ground truth beside it). OpenCV decodes
AVI at a few thousand frames/s, well under the camera's 19,000, so the first start copies it once
into an 8-bit .cine in the data folder, which replays memory-mapped at any rate.
"""

from __future__ import annotations

import os
import shutil
from importlib.resources import files
from pathlib import Path

from service.recordings import open_recording, open_writer
from service.sources.replay import replay_uri

#: The shipped recording and its ground truth (scene.md, "Recordings and ground truth").
DEMO_AVI = Path(str(files("service") / "demo" / "demo.avi"))
DEMO_TRUTH = DEMO_AVI.with_name("demo.truth.json")


def demo_recording(data_dir: Path) -> Path:
    """``DATA_DIR/demo/demo.cine`` (with ``demo.truth.json``), made from the shipped AVI if it is not there."""
    folder = data_dir / "demo"
    cine = folder / "demo.cine"
    if cine.is_file():
        return cine
    folder.mkdir(parents=True, exist_ok=True)
    partial = folder / f".demo.{os.getpid()}.cine"  # renamed when complete: a crash leaves no half file
    with open_recording(DEMO_AVI) as avi, open_writer(partial, avi.width, avi.height, avi.fps, 8) as writer:
        writer.write(avi.read(0, len(avi)))
    shutil.copyfile(DEMO_TRUTH, folder / "demo.truth.json")
    partial.replace(cine)
    return cine


def demo_uri(data_dir: Path) -> str:
    """The demo source: the recording replayed at the camera's rate, looping."""
    return replay_uri(demo_recording(data_dir), speed=1, loop=1)
