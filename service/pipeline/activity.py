"""Frame activity as frames stream in: how much each frame differs from the one before, as a robust z-score.

The change of each frame (the mean absolute difference from the previous frame over every pixel,
:class:`service.pipeline.measures.PixelMeasures`: a subsampled change placed an ejection's onset a frame late in
about one window in ten, which offline detection, reading the same changes, would inherit) is scored against the
median and MAD of the last ``history`` frames rather than the whole recording, so that a live stream's score needs
no look-ahead; none before ``warmup`` changes were seen.
"""

from __future__ import annotations

import numpy as np

from service.analysis.segment import robust_z


class ActivityTracker:
    """Per-frame activity z-scores of one stream's frame changes, across consecutive batches."""

    def __init__(self, history: int = 2048, warmup: int = 64) -> None:
        self.history, self.warmup = history, warmup
        self._steps = np.empty(0)

    def score(self, steps: np.ndarray) -> np.ndarray:
        """Z-scores (N,) of the next frames' changes ``steps`` (N,) (NaN where a frame has none: 0 there)."""
        scored = robust_z(np.concatenate([self._steps, steps]))[-len(steps) :]
        known = self._steps.size + np.cumsum(np.isfinite(steps))  # changes seen up to each frame
        self._steps = np.concatenate([self._steps, steps[np.isfinite(steps)]])[-self.history :]
        # a score against fewer than ``warmup`` changes is noise (a stream's first frames scored each other as
        # ejections: a 2-frame window at every start): 0 until then
        return np.where(np.isfinite(steps) & (known >= self.warmup), scored, 0.0)
