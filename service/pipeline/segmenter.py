"""Live segmentation: the centre-displacement stream cut into windows at ejections, as frames arrive.

The causal counterpart of :mod:`service.analysis.segment` (same :class:`Window` conventions): an
ejection is the first frame whose activity rises above the threshold, at least ``min_gap`` frames
after the previous ejection (half the expected period), so it is known the moment its frame is
inferred and the window before it closes at once. Frames lost on the way (source gaps, frames the
service dropped) become NaN samples, which the fit skips; a window that outgrows ``max_frames`` or a
gap that long is cut there (its end is then not an ejection), so memory stays bounded.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from service.analysis.segment import Window


@dataclass(frozen=True)
class ClosedWindow:
    """A window whose frames are all in: its place in the stream, its samples and when it closed.

    ``values``: (end - start, ...) what was pushed per frame (the live pipeline's d, p, a, b and brightness;
    after its dispatch, the steady D(0, t)), NaN where frames are missing;
    ``closed_at``: monotonic time (s) the frame that closed it was acquired;
    ``brightness``: (end - start,) the frames' mean brightness, where the fit takes its poles from the frames.
    """

    window: Window
    values: np.ndarray
    closed_at: float
    brightness: np.ndarray | None = None


class StreamingSegmenter:
    """Cuts consecutive batches of (frame index, per-frame values, activity, arrival time) into closed windows."""

    def __init__(self, min_gap: int, max_frames: int, threshold: float) -> None:
        self.min_gap, self.max_frames, self.threshold = max(1, min_gap), max(2, max_frames), threshold
        self.ejections: deque[int] = deque(maxlen=256)  # recent ejection frames, for the live trace
        self._count = 0  # windows closed so far: the next one's index
        self._next: int | None = None  # the frame index expected next
        self._start = 0
        self._at_ejection = False
        self._pieces: list[np.ndarray] = []
        self._length = 0
        self._above = False  # whether the last frame's activity was above the threshold
        self._last_ejection: int | None = None

    def push(self, indices: np.ndarray, values: np.ndarray, activity: np.ndarray,
             arrival: np.ndarray) -> list[ClosedWindow]:
        """Add a batch (indices, activity, arrival (N,), increasing; values (N, ...)); the windows it closes."""
        closed: list[ClosedWindow] = []
        if self._next is not None and indices[0] - self._next >= self.max_frames:
            closed += self._close(False, float(arrival[0]))  # a gap as long as a window: start afresh
            self._next, self._at_ejection = None, False
        first = int(indices[0]) if self._next is None else self._next
        dense = np.arange(first, int(indices[-1]) + 1)
        slot = indices - first
        x = np.full((dense.size, *np.shape(values)[1:]), np.nan)
        x[slot] = values
        z = np.zeros(dense.size)
        z[slot] = activity
        when = np.full(dense.size, np.inf)
        when[slot] = arrival
        when = np.minimum.accumulate(when[::-1])[::-1]  # a missing frame counts as arriving with the next one
        if self._length == 0:
            self._start = first
        above = z > self.threshold
        rising = np.flatnonzero(above & ~np.concatenate([[self._above], above[:-1]]))
        self._above = bool(above[-1])
        i = 0
        for cut in [*self._ejections(dense, rising), dense.size]:
            while i < cut:
                take = min(cut - i, self.max_frames - self._length)
                self._append(x[i : i + take])
                i += take
                if self._length >= self.max_frames:
                    closed += self._close(False, float(when[i - 1]))
                    self._start, self._at_ejection = int(dense[i - 1]) + 1, False
            if cut < dense.size:
                closed += self._close(True, float(when[cut]))
                self._start, self._at_ejection = int(dense[cut]), True
                self.ejections.append(int(dense[cut]))
        self._next = int(dense[-1]) + 1
        return closed

    def finish(self, closed_at: float) -> list[ClosedWindow]:
        """The stream ended: the window in progress, closed there (its end is not an ejection)."""
        return self._close(False, closed_at)

    def _ejections(self, dense: np.ndarray, rising: np.ndarray) -> list[int]:
        """Positions (in ``dense``) of the rising edges at least ``min_gap`` frames after the previous ejection."""
        kept = []
        for pos in rising:
            frame = int(dense[pos])
            if self._last_ejection is None or frame - self._last_ejection >= self.min_gap:
                kept.append(int(pos))
                self._last_ejection = frame
        return kept

    def _append(self, values: np.ndarray) -> None:
        if len(values):
            self._pieces.append(values)
            self._length += len(values)

    def _close(self, at_ejection: bool, closed_at: float) -> list[ClosedWindow]:
        """The current window as a closed one (none if it is empty), and an empty one started."""
        if self._length == 0:
            return []
        values = np.concatenate(self._pieces)
        window = Window(self._count, self._start, self._start + len(values), self._at_ejection, at_ejection)
        self._count += 1
        self._pieces, self._length = [], 0
        return [ClosedWindow(window, values, closed_at)]
