"""What the pixels alone say about each frame, in one pass over them: its change from the frame before, its
mean brightness and its brightest pixel.

One compiled loop (numba) reads each pixel once for all three (three numpy reductions and OpenCV's difference
read them four times: 9.3 us per 96 x 96 16-bit frame against 3.2 here), with exact sums: integer pixels are
summed in 64-bit integers, so that the results are the same to the last bit as the exact means they replace.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _sums(frames, previous, zero, total, peak, change):  # type: ignore[no-untyped-def]
    """Per frame of ``frames`` (N, P): its pixels' sum, maximum and summed absolute difference from the frame
    before (``previous`` (P,) before frame 0), accumulated from ``zero`` (its type sets the sums')."""
    for i in range(frames.shape[0]):
        row = frames[i]
        before = previous if i == 0 else frames[i - 1]
        s, d, m = zero, zero, row[0]
        for j in range(row.shape[0]):
            a, b = row[j], before[j]
            s += a
            m = max(m, a)
            d += max(a, b) - min(a, b)  # |a - b| without leaving the unsigned type
        total[i], peak[i], change[i] = s, m, d


class PixelMeasures:
    """Per-frame pixel measures across consecutive batches of one stream (the frame before a batch's first is
    kept, so that a batch boundary changes nothing)."""

    def __init__(self) -> None:
        self._previous: np.ndarray | None = None  # last frame of the previous batch, flattened
        self._last_index: int | None = None

    def update(self, pixels: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Of frames ``pixels`` (N, H, W) with frame ``indices`` (N,): each one's change (mean absolute difference
        from the frame before, NaN at the stream's first frame and after a gap), mean and maximum, (N,) float64
        each, in pixel units."""
        n = len(pixels)
        flat = pixels.reshape(n, -1)
        if not np.issubdtype(flat.dtype, np.unsignedinteger):  # an unsigned sum of signed pixels would wrap
            flat = flat.astype(np.float64)
        zero = np.uint64(0) if flat.dtype.kind == "u" else np.float64(0.0)
        follows = self._previous is not None and self._last_index == indices[0] - 1
        total, change, peak = np.empty(n, zero.dtype), np.empty(n, zero.dtype), np.empty(n, flat.dtype)
        _sums(flat, self._previous if follows else flat[0], zero, total, peak, change)
        size = flat.shape[1]
        steps = change / size
        if not follows:
            steps[0] = np.nan
        steps[1:][np.diff(indices) != 1] = np.nan  # no change across frames lost in between
        self._previous, self._last_index = flat[-1].copy(), int(indices[-1])  # the batch buffer may be reused
        return steps, total / size, peak.astype(np.float64)
