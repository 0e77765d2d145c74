"""Window assembly: the per-frame records cut into windows at ejections, as frames arrive.

The one segmenter of every front door (same :class:`Window` conventions as
:mod:`service.analysis.segment`). Live, the ejections come from an
:class:`service.pipeline.ejections.EjectionDetector` fed each batch's frame change: frames wait in the
segmenter until the detector has decided them (its look-ahead, a few frames), so a window closes a few
frames after its ejection. Offline feeds the same detector with a longer look-ahead, or hands the ejections
the printer's file or a known rate placed to :meth:`StreamingSegmenter.push` with the frames; the windows are cut
by the same code. Frames lost on the way (source gaps, frames the service dropped) become NaN
records, which the fit skips; a window that outgrows ``max_frames`` or a gap that long is cut there
(its end is then not an ejection), so memory stays bounded.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from service.analysis.segment import Window
from service.pipeline.ejections import EjectionDetector
from service.pipeline.trigger import TriggerCheck


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
    """Cuts consecutive batches of (frame index, per-frame values, frame change, arrival time) into closed windows.

    ``drop_leading``: the window before the stream's first ejection (when the stream does not start at one) is
    not returned, though it keeps its index: its frames are the end of a window whose ejection was never seen,
    so it has no t = 0 to fit from (the live service starts and restarts anywhere in a window).
    """

    def __init__(
        self,
        max_frames: int,
        detector: EjectionDetector | None = None,
        drop_leading: bool = False,
        trigger: TriggerCheck | None = None,
    ) -> None:
        self.max_frames, self.detector, self.drop_leading = max(2, max_frames), detector, drop_leading
        self.trigger = trigger  # with one (and a detector), the printer's ejections cut and the video's check them
        self._waiting: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (indices, values, arrival) undecided
        self._found: list[int] = []  # ejections the detector found that are not yet cut
        self._seen_ejection = False
        self.ejections: deque[int] = deque(maxlen=256)  # recent ejection frames, for the live trace
        self._count = 0  # windows closed so far: the next one's index
        self._next: int | None = None  # the frame index expected next
        self._start = 0
        self._at_ejection = False
        self._pieces: list[np.ndarray] = []
        self._length = 0

    def push(
        self,
        indices: np.ndarray,
        values: np.ndarray,
        change: np.ndarray,
        arrival: np.ndarray,
        ejections: np.ndarray | None = None,
        novelty: np.ndarray | None = None,
    ) -> list[ClosedWindow]:
        """Add a batch (indices, change, arrival and novelty (N,), increasing; values (N, ...)); the windows it
        closes (the detector judges without novelty where it is None).

        ``ejections``: the ejection frames among ``indices`` when they are known already (offline, which looks
        further ahead); else the detector's (or the printer's trigger's, which the detector's then check), the
        batch's frames waiting until they are decided."""
        if ejections is not None or self.detector is None:
            return self._cut(indices, values, arrival, np.empty(0, np.int64) if ejections is None else ejections)
        found = self.detector.push(indices, change, novelty)
        self._waiting.append((np.asarray(indices), np.asarray(values), np.asarray(arrival)))
        if self.trigger is None:
            self._found += found
            return self._release(self.detector.settled)
        until = self.trigger.update(found, int(indices[-1]), self.detector.settled)
        self._found = self.trigger.cuts
        return self._release(until)

    def _release(self, until: int) -> list[ClosedWindow]:
        """Cut the waiting frames before ``until`` (decided by the detector) at the ejections it found."""
        if not self._waiting:
            return []
        indices, values, arrival = (np.concatenate(parts) for parts in zip(*self._waiting))
        ready = indices < until
        self._waiting = [(indices[~ready], values[~ready], arrival[~ready])] if not ready.all() else []
        if not ready.any():
            return []
        cuts = np.asarray(self._found, np.int64)
        self._found[:] = [f for f in self._found if f >= until]
        return self._cut(indices[ready], values[ready], arrival[ready], cuts)

    def _cut(
        self, indices: np.ndarray, values: np.ndarray, arrival: np.ndarray, ejections: np.ndarray
    ) -> list[ClosedWindow]:
        """Cut a decided batch at ``ejections``; the windows it closes."""
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
        when = np.full(dense.size, np.inf)
        when[slot] = arrival
        when = np.minimum.accumulate(when[::-1])[::-1]  # a missing frame counts as arriving with the next one
        if self._length == 0:
            self._start = first
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
        """The stream ended: the frames still waiting cut at what the detector finds in them, then the window in
        progress, closed there (its end is not an ejection)."""
        if self.detector is not None:
            found = self.detector.finish()
            if self.trigger is None:
                self._found += found
            else:
                self.trigger.update(found, np.iinfo(np.int64).max - 1, np.iinfo(np.int64).max)
                self._found = self.trigger.cuts
        return self._release(np.iinfo(np.int64).max) + self._close(False, closed_at)

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
