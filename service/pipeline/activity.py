"""Frame activity as frames stream in: how much each frame differs from the one before, as a robust z-score.

The mean absolute difference from the previous frame (:func:`service.analysis.segment.frame_steps`, exact
integer sums), on every ``stride``-th pixel in each direction (1 by default: a subsampled change places an
ejection's onset a frame late in about one window in ten, which offline detection, reading the same changes,
would inherit), scored against the median and MAD of the last ``history`` frames rather than the whole
recording, so that a live stream's score needs no look-ahead; none before ``warmup`` changes were seen.
"""

from __future__ import annotations

import numpy as np

from service.analysis.segment import frame_steps, robust_z


class ActivityTracker:
    """Per-frame activity z-scores across consecutive batches of one stream."""

    def __init__(self, stride: int = 1, history: int = 2048, warmup: int = 64) -> None:
        self.stride, self.history, self.warmup = stride, history, warmup
        self._previous: np.ndarray | None = None  # last frame of the previous batch, subsampled
        self._last_index: int | None = None
        self._steps = np.empty(0)

    def update(self, pixels: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Changes (N,) of frames ``pixels`` (N, H, W) with frame ``indices`` (N,) from the frame before (NaN at the
        stream's first frame and after a gap) and their z-scores (N,) (0 there)."""
        x = pixels[:, :: self.stride, :: self.stride]
        follows = self._previous is not None and self._last_index == indices[0] - 1
        steps = frame_steps(x, self._previous if follows else None)  # NaN at frame 0 unless it follows
        steps[1:][np.diff(indices) != 1] = np.nan  # no step across frames lost in between
        self._previous, self._last_index = x[-1].copy(), int(indices[-1])  # the batch buffer may be reused
        scored = robust_z(np.concatenate([self._steps, steps]))[-len(steps) :]
        known = self._steps.size + np.cumsum(np.isfinite(steps))  # changes seen up to each frame
        self._steps = np.concatenate([self._steps, steps[np.isfinite(steps)]])[-self.history :]
        # a score against fewer than ``warmup`` changes is noise (a stream's first frames scored each other as
        # ejections: a 2-frame window at every start): 0 until then
        return steps, np.where(np.isfinite(steps) & (known >= self.warmup), scored, 0.0)
