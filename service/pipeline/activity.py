"""Live frame activity: how much each frame differs from the one before, as a robust z-score.

The streaming counterpart of :func:`service.analysis.segment.frame_activity`: the mean absolute
difference from the previous frame, taken on every ``stride``-th pixel in each direction (a 96 x 96
ROI at stride 3 is 32 x 32 pixels, ~10x cheaper and just as sharp at an ejection, whose bulge
moves every highlight), scored against the median and MAD of the last ``history`` frames rather
than the whole recording.
"""
from __future__ import annotations

import numpy as np

from service.analysis.segment import frame_steps, robust_z


class ActivityTracker:
    """Per-frame activity z-scores across consecutive batches of one stream."""

    def __init__(self, stride: int = 3, history: int = 2048) -> None:
        self.stride, self.history = stride, history
        self._previous: np.ndarray | None = None  # last frame of the previous batch, subsampled
        self._last_index: int | None = None
        self._steps = np.empty(0)

    def update(self, pixels: np.ndarray, indices: np.ndarray) -> np.ndarray:
        """z-scores (N,) of frames ``pixels`` (N, H, W) with frame ``indices`` (N,); 0 after a gap."""
        x = pixels[:, :: self.stride, :: self.stride]
        follows = self._previous is not None and self._last_index == indices[0] - 1
        steps = frame_steps(x, self._previous if follows else None)  # NaN at frame 0 unless it follows
        steps[1:][np.diff(indices) != 1] = np.nan  # no step across frames lost in between
        self._previous, self._last_index = x[-1].copy(), int(indices[-1])  # the batch buffer may be reused
        scored = robust_z(np.concatenate([self._steps, steps]))[-len(steps):]
        self._steps = np.concatenate([self._steps, steps[np.isfinite(steps)]])[-self.history:]
        return np.where(np.isfinite(steps), scored, 0.0)
