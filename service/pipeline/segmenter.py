"""Window assembly: the per-frame records cut into windows at ejections, as frames arrive.

The one segmenter of every front door (same :class:`Window` conventions as
:mod:`service.analysis.segment`). Live, an ejection is the first frame whose activity rises above
the threshold, at least ``min_gap`` frames after the previous ejection (half the expected period),
so it is known the moment its frame is inferred and the window before it closes at once. Offline
looks further ahead (the printer's file, a known rate, or detection over the whole recording) and
hands the ejections it found to :meth:`StreamingSegmenter.push` with the frames; the windows are cut
by the same code. Frames lost on the way (source gaps, frames the service dropped) become NaN
records, which the fit skips; a window that outgrows ``max_frames`` or a gap that long is cut there
(its end is then not an ejection), so memory stays bounded.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from service.analysis.segment import Window


@dataclass(frozen=True)
class ClosedWindow:
    """A window whose frames are all in: its place in the stream, its samples and when it closed.

    ``values``: (end - start, ...) what was pushed per frame (the pipeline's records,
    :data:`service.pipeline.records.FRAME`), NaN where frames are missing;
    ``closed_at``: monotonic time (s) the frame that closed it was acquired.
    """

    window: Window
    values: np.ndarray
    closed_at: float


class StreamingSegmenter:
    """Cuts consecutive batches of (frame index, per-frame values, activity, arrival time) into closed windows.

    ``drop_leading``: the window before the stream's first ejection (when the stream does not start at one) is
    not returned, though it keeps its index: its frames are the end of a window whose ejection was never seen,
    so it has no t = 0 to fit from (the live service starts and restarts anywhere in a window).
    """

    def __init__(self, min_gap: int, max_frames: int, threshold: float, drop_leading: bool = False) -> None:
        self.min_gap, self.max_frames, self.threshold = max(1, min_gap), max(2, max_frames), threshold
        self.drop_leading = drop_leading
        self._seen_ejection = False
        self.ejections: deque[int] = deque(maxlen=256)  # recent ejection frames, for the live trace
        self._count = 0  # windows closed so far: the next one's index
        self._next: int | None = None  # the frame index expected next
        self._start = 0
        self._at_ejection = False
        self._pieces: list[np.ndarray] = []
        self._length = 0
        self._above = False  # whether the last frame's activity was above the threshold
        self._last_ejection: int | None = None

    def push(
        self,
        indices: np.ndarray,
        values: np.ndarray,
        activity: np.ndarray,
        arrival: np.ndarray,
        ejections: np.ndarray | None = None,
    ) -> list[ClosedWindow]:
        """Add a batch (indices, activity, arrival (N,), increasing; values (N, ...)); the windows it closes.

        ``ejections``: the ejection frames among ``indices`` when they are known already (offline, which looks
        further ahead); the activity's rising edges are then not consulted."""
        closed: list[ClosedWindow] = []
        if self._next is not None and indices[0] - self._next >= self.max_frames:
            closed += self._close(False, float(arrival[0]))  # a gap as long as a window: start afresh
            self._next, self._at_ejection = None, False
        first = int(indices[0]) if self._next is None else self._next
        dense = np.arange(first, int(indices[-1]) + 1)
        slot = indices - first
        values = np.asarray(values)
        x = np.full((dense.size, *values.shape[1:]), np.nan, values.dtype if values.dtype.names else np.float64)
        x[slot] = values
        z = np.zeros(dense.size)
        z[slot] = activity
        when = np.full(dense.size, np.inf)
        when[slot] = arrival
        when = np.minimum.accumulate(when[::-1])[::-1]  # a missing frame counts as arriving with the next one
        if self._length == 0:
            self._start = first
        if ejections is None:
            above = z > self.threshold
            rising = np.flatnonzero(above & ~np.concatenate([[self._above], above[:-1]]))
            self._above = bool(above[-1])
            cuts = self._ejections(dense, rising)
        else:
            cuts = np.flatnonzero(np.isin(dense, ejections)).tolist()
        i = 0
        for cut in [*cuts, dense.size]:
            while i < cut:
                take = min(cut - i, self.max_frames - self._length)
                self._append(x[i : i + take])
                i += take
                if self._length >= self.max_frames:
                    closed += self._close(False, float(when[i - 1]))
                    self._start, self._at_ejection = int(dense[i - 1]) + 1, False
            if cut < dense.size:
                closed += self._close(True, float(when[cut]))
                self._start, self._at_ejection, self._seen_ejection = int(dense[cut]), True, True
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
        if self.drop_leading and not self._seen_ejection:  # the tail of a window whose ejection was not seen
            return []
        return [ClosedWindow(window, values, closed_at)]
