"""The scene's region of interest of a recording, streamed in chunks so that any length fits in memory."""
from __future__ import annotations

from typing import Iterator

import numpy as np

from service.recordings.base import Recording
from service.scene import Scene


def roi_chunks(recording: Recording, scene: Scene, chunk: int = 1024) -> Iterator[tuple[int, np.ndarray]]:
    """(first frame index, ROI frames (n, H, W) as stored) for consecutive chunks of ``chunk`` frames.

    The ROI (``camera.roi``, ``width_px`` x ``height_px``) is checked against the frame size first,
    so a recording of another camera is one clear error, not a silently wrong crop.
    """
    cam = scene.camera
    x, y = cam.roi
    scene.check_roi(recording.width, recording.height, recording.path)
    for start in range(0, len(recording), chunk):
        frames = recording.read(start, min(chunk, len(recording) - start))
        yield start, np.ascontiguousarray(frames[:, y : y + cam.height_px, x : x + cam.width_px])
