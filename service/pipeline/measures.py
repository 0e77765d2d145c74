"""What the pixels alone say about each frame, in one pass over them: its change from the frame before, its
mean brightness, its brightest pixel, and how new its coarse picture is.

One compiled loop (numba) reads each pixel once for all of them (three numpy reductions and OpenCV's difference
read them four times), with exact sums of integer pixels (the column sums held in 32-bit integers, 64-bit where a
frame's sum could pass 2**32; the frame's own running sums numba carries in 64 bits), so that the results are the
same to the last bit as the exact means they replace.

Novelty is the distance (mean absolute difference of the :data:`GRID` x :data:`GRID` cells' means) from the
frame to the nearest of the frames ``near .. far`` before it: ringing, however strong, keeps returning to the
shapes of its last period, so its frames stay near earlier ones; an ejection's bulge is a shape the meniscus
has not shown lately (:mod:`service.pipeline.ejections` uses it where the amount of change does not stand out).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numba import njit

from service.inverse.pooling import standardise_frame

#: The coarse picture novelty compares: the frame's means over GRID x GRID cells (fewer where the frame is
#: smaller); 64 numbers keep the comparison with tens of earlier frames at about a microsecond.
GRID = 8


@njit(cache=True, nogil=True)
def _sums(words, starts, previous, zero, band, edges, flipped, total, peak, change, cells, factor, pooled, standardise):  # type: ignore[no-untyped-def]
    """Per frame ``words[starts[i] : starts[i] + H * W]`` (its rows in memory order: bottom row first where
    ``flipped``): its pixels' sum, maximum and summed absolute difference from the frame before (``previous``
    (H * W,), in the same row order, before frame 0), accumulated from ``zero`` (its type sets the sums'), and its
    sums over the cells (``cells`` (N, bands * columns)): memory row r in band ``band[r]``, columns cut at ``edges``
    (columns + 1,). A band's rows are summed column by column first (a plain loop over each row, as fast as the
    three sums alone), then cut into its cells. With ``factor`` > 0, also the means of its ``factor`` x ``factor``
    blocks into ``pooled`` (N, 1, H/f, W/f) in display order, summed the same way (exact sums of integer pixels,
    divided once); with ``standardise``, each frame's block means then standardised as the graphs' normalisation
    does (:func:`service.inverse.pooling.standardise_frame`, their sums gathered by block column as they are made).
    Rows are read in memory order, as the hardware prefetches them."""
    columns = edges.size - 1
    width = edges[columns]
    height = band.size
    size = height * width
    acc = np.full(width, zero)
    block = np.full(width, zero)
    sums = np.zeros(width // factor if factor else 0)  # the frame's block means summed by block column, and squared
    squares = np.zeros_like(sums)
    for i in range(starts.size):
        row = words[starts[i] : starts[i] + size]
        before = previous if i == 0 else words[starts[i - 1] : starts[i - 1] + size]
        s, d, m = zero, zero, row[0]
        for y in range(height):
            for x in range(width):
                j = y * width + x
                a, b = row[j], before[j]
                s += a
                m = max(m, a)
                d += max(a, b) - min(a, b)  # |a - b| without leaving the unsigned type
                acc[x] += a
                block[x] += a
            if factor:
                if (y + 1) % factor == 0:  # the block row's last row: its blocks
                    out = pooled[i, 0, (height - 1 - y) // factor if flipped else y // factor]
                    # the shipped graphs pool by 3: unrolled, as the general loop's short inner loop is slow
                    if factor == 3:
                        for c in range(width // 3):
                            out[c] = np.float64(block[3 * c] + block[3 * c + 1] + block[3 * c + 2]) / 9.0
                    else:
                        for c in range(width // factor):
                            t = zero
                            for k in range(c * factor, c * factor + factor):
                                t += block[k]
                            out[c] = np.float64(t) / (factor * factor)
                    if standardise:
                        for c in range(width // factor):
                            v = np.float64(out[c])
                            sums[c] += v
                            squares[c] += v * v
                    block[:] = zero
            if y + 1 == height or band[y + 1] != band[y]:  # the band's last row: its cells
                for c in range(columns):
                    cells[i, band[y] * columns + c] = acc[edges[c] : edges[c + 1]].sum()
                acc[:] = zero
        total[i], peak[i], change[i] = s, m, d
        if standardise:
            standardise_frame(pooled[i].reshape(-1), sums.sum(), squares.sum())
            sums[:] = 0.0
            squares[:] = 0.0


def _words(pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Frames ``pixels`` (N, H, W) as the compiled pass reads them, without a copy where each frame's rows lie next
    to each other in memory (a C-contiguous batch, or a .cine's frames viewed in its mapping: rows bottom-up, frames
    at the file's stride): (words (M,), each frame's first word in memory (N,), whether its rows run bottom-up)."""
    n, h, w = pixels.shape
    item = pixels.itemsize
    frame_step, row_step, column_step = pixels.strides
    together = column_step == item and abs(row_step) == w * item and frame_step >= 0 and frame_step % item == 0
    if pixels.flags.c_contiguous or not together:
        pixels = np.ascontiguousarray(pixels)
        return pixels.reshape(-1), np.arange(n, dtype=np.int64) * (h * w), False
    flipped = row_step < 0
    lowest = pixels[0, h - 1] if flipped else pixels[0, 0]  # the first frame's first row in memory
    words = np.lib.stride_tricks.as_strided(lowest, ((n - 1) * frame_step // item + h * w,), (item,), writeable=False)
    return words, np.arange(n, dtype=np.int64) * (frame_step // item), flipped


@njit(cache=True, nogil=True)
def _novelty(cells, ring, filled, position, near, out):  # type: ignore[no-untyped-def]
    """Each row of ``cells`` (N, C): its mean absolute distance to the nearest of the frames ``near`` .. ``filled``
    before it held in ``ring`` (C, F) (the last F frames by column, the newest at ``position - 1``); NaN with none
    that far back. Each row then enters the ring; returns the ring's fill and next position. The distances to all F
    are summed together, cell by cell (each in the order of its cells, as one at a time would)."""
    width, size = ring.shape
    distance = np.empty(size)
    for i in range(cells.shape[0]):
        distance[:] = 0.0
        for k in range(width):
            c = cells[i, k]
            for f in range(size):
                distance[f] += abs(c - ring[k, f])
        best = np.inf
        for lag in range(near, filled + 1):
            best = min(best, distance[(position - lag) % size])
        out[i] = best / width if best < np.inf else np.nan
        ring[:, position] = cells[i]
        position = (position + 1) % size
        filled = min(filled + 1, size)
    return filled, position


def _zero(dtype: np.dtype, pixels: int) -> np.generic:
    """The zero the sums of frames of ``pixels`` pixels of ``dtype`` start from, whose type the column sums and the
    returned totals are kept in (numba widens the running scalar sums to 64 bits): 32-bit unsigned where a frame's
    pixels all at full scale sum below 2**32, 64-bit unsigned where not, float64 for pixels that are not unsigned
    integers."""
    if dtype.kind != "u":
        return np.float64(0.0)
    return np.uint32(0) if pixels * int(np.iinfo(dtype).max) < 2**32 else np.uint64(0)


class PixelMeasures:
    """Per-frame pixel measures across consecutive batches of one stream (the frame before a batch's first, and
    the novelty's last frames, are kept, so that a batch boundary changes nothing).

    ``near``, ``far``: the frames novelty compares with (:func:`service.pipeline.ejections.novelty_lags`)."""

    def __init__(self, near: int, far: int) -> None:
        self._previous: np.ndarray | None = None  # last frame of the previous batch, flattened
        self._last_index: int | None = None
        self._near, self._far = max(1, near), max(near, far, 1)
        self._ring: np.ndarray | None = None  # the last ``far`` frames' cell means, a column each
        self._filled, self._position = 0, 0
        self._shape: tuple[int, int] | None = None  # the frames' size the cell numbers below are for
        self._band, self._edges, self._counts = np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0)

    def update(
        self, pixels: np.ndarray, indices: np.ndarray, pooled: np.ndarray | None = None, standardise: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Of frames ``pixels`` (N, H, W) with frame ``indices`` (N,): each one's change (mean absolute difference
        from the frame before, NaN at the stream's first frame and after a gap), mean, maximum and novelty (NaN
        until ``near`` frames are in since the start or a gap), (N,) float64 each, in pixel units. Where given,
        ``pooled`` (N, 1, H/f, W/f) float32 gets each frame's f x f block means in the same pass (an inverse graph's
        input, :attr:`service.inverse.base.InverseMethod.pooling`), the exact means rounded once, and with
        ``standardise`` those then standardised frame by frame (:func:`service.inverse.pooling.standardise`)."""
        n, h, w = pixels.shape
        if not np.issubdtype(pixels.dtype, np.unsignedinteger):  # an unsigned sum of signed pixels would wrap
            pixels = pixels.astype(np.float64)
        zero = _zero(pixels.dtype, h * w)
        follows = self._previous is not None and self._last_index == indices[0] - 1
        band, edges, counts = self._cells(h, w)
        total, change, peak = np.empty(n, zero.dtype), np.empty(n, zero.dtype), np.empty(n, pixels.dtype)
        cells = np.zeros((n, counts.size))
        factor = 0
        if pooled is None:
            pooled = np.empty((0, 1, 0, 0), np.float32)
        else:
            factor = h // pooled.shape[2] if pooled.ndim == 4 and pooled.shape[2] else 0
            if not factor or pooled.shape != (n, 1, h // factor, w // factor) or h % factor or w % factor:
                raise ValueError(f"pooled must be (N, 1, H/f, W/f) of whole blocks, got {pooled.shape} for {h} x {w}")
            if pooled.dtype != np.float32:
                raise ValueError(f"pooled must be float32, got {pooled.dtype}")
        words, starts, flipped = _words(pixels)
        previous = self._previous if follows else pixels[0].reshape(-1)  # display order
        if flipped:  # in the order the pass reads the rows
            band, previous = band[::-1].copy(), previous.reshape(h, w)[::-1].ravel()
        _sums(
            words, starts, previous, zero, band, edges, flipped, total, peak, change, cells, factor, pooled, standardise
        )
        size = h * w
        steps = change / size
        if not follows:
            steps[0] = np.nan
        breaks = np.flatnonzero(np.diff(indices) != 1) + 1
        steps[breaks] = np.nan  # no change across frames lost in between
        novelty = np.empty(n)
        cells /= counts
        if self._ring is None or self._ring.shape[0] != counts.size:
            self._ring, self._filled, self._position = np.zeros((counts.size, self._far)), 0, 0
        for lo, hi in zip([0, *breaks], [*breaks, n]):  # a gap starts the comparison afresh
            if lo > 0 or not follows:
                self._filled = 0
            self._filled, self._position = _novelty(
                cells[lo:hi], self._ring, self._filled, self._position, self._near, novelty[lo:hi]
            )
        self._previous, self._last_index = pixels[-1].flatten(), int(indices[-1])  # the batch buffer may be reused
        return steps, total / size, peak.astype(np.float64), novelty

    def _cells(self, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For frames of ``h`` x ``w``: each row's band (H,) (row y in band y * GRID // H), the column edges of the
        cells (column x in cell x * GRID // W) and each cell's pixel count, GRID x GRID cells (fewer where the frame
        is smaller)."""
        if self._shape != (h, w):
            gy, gx = min(GRID, h), min(GRID, w)
            self._shape = (h, w)
            self._band = np.arange(h) * gy // h
            self._edges = np.searchsorted(np.arange(w) * gx // w, np.arange(gx + 1))
            self._counts = np.outer(np.bincount(self._band, minlength=gy), np.diff(self._edges)).ravel().astype(float)
        return self._band, self._edges, self._counts


def recording_measures(recording: Path, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's change and novelty (N,) over a whole recording's frames, as the pipeline measures them: what the
    ejection detector reads, for a recording read outside the pipeline (``calibrate``, ``bench ejections``)."""
    from service.pipeline.ejections import novelty_lags
    from service.recordings import open_recording

    pixels = PixelMeasures(*novelty_lags(fps))
    change, novelty = [], []
    with open_recording(recording) as rec:
        for lo in range(0, len(rec), 512):
            frames = rec.read_grey(lo, min(512, len(rec) - lo))
            c, _, _, v = pixels.update(frames, np.arange(lo, lo + len(frames)))
            change.append(c)
            novelty.append(v)
    return np.concatenate(change), np.concatenate(novelty)
