"""The scene's region of interest read out of a recording, as stored (a colour camera's mosaic demosaiced
to grey first: :meth:`Recording.read_grey`): what every inverse method takes; whole (evenly spaced runs,
for training) or streamed in chunks (any length, for analysis)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from tqdm import tqdm

from service.errors import MeniscopeError
from service.recordings import open_recording
from service.recordings.base import Recording
from service.scene import Scene


def read_roi_frames(
    path: str | Path, scene: Scene, limit: int | None = None, run: int = 512
) -> tuple[np.ndarray, dict]:
    """The scene's ROI of a recording, as stored: (N, H, W) uint8 | uint16, and facts about it.

    With ``limit`` below the frame count, ``limit`` frames are read as evenly spaced runs of at
    most ``run`` consecutive frames, so that every part of the recording is represented.
    """
    path = Path(path)
    cam = scene.camera
    x, y = cam.roi
    with open_recording(path) as rec:
        scene.check_roi(rec.width, rec.height, path)
        total = len(rec)
        if total == 0:
            raise MeniscopeError(path, "the recording holds no frames")
        take = total if limit is None else min(limit, total)
        runs = math.ceil(take / run)
        starts = np.linspace(0, total, runs + 1).astype(int)[:-1]  # (runs,), spaced >= take / runs
        counts = np.diff(np.linspace(0, take, runs + 1).astype(int))  # (runs,), summing to take
        out = np.empty((take, cam.height_px, cam.width_px), rec.dtype)  # (N, H, W)
        done = 0
        for start, count in tqdm(zip(starts, counts), total=runs, desc=f"read {path.name}", unit="run", disable=None):
            out[done : done + count] = rec.read_grey(int(start), int(count))[
                :, y : y + cam.height_px, x : x + cam.width_px
            ]
            done += count
        facts = {
            "path": str(path),
            "frames_total": total,
            "frames_used": take,
            "fps": rec.fps,
            "width": rec.width,
            "height": rec.height,
            "bit_depth": rec.bit_depth,
        }
    return out, facts


def roi_chunks(recording: Recording, scene: Scene, chunk: int = 1024) -> Iterator[tuple[int, np.ndarray]]:
    """(first frame index, ROI frames (n, H, W) as stored) for consecutive chunks of ``chunk`` frames.

    The ROI (``camera.roi``, ``width_px`` x ``height_px``) is checked against the frame size first,
    so a recording of another camera is one clear error, not a silently wrong crop.
    """
    scene.check_roi(recording.width, recording.height, recording.path)
    for start in range(0, len(recording), chunk):
        yield start, roi_frames(recording, scene, start, min(chunk, len(recording) - start))


def roi_frames(recording: Recording, scene: Scene, start: int, count: int) -> np.ndarray:
    """The ROI of ``count`` frames from ``start``, (count, H, W) as stored (the ROI checked by the caller)."""
    cam = scene.camera
    x, y = cam.roi
    frames = recording.read_grey(start, count)
    return np.ascontiguousarray(frames[:, y : y + cam.height_px, x : x + cam.width_px])
