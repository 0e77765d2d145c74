"""Ejections found from their own signature, as frames stream in: one detector for live and offline.

An ejection (the droplet leaving, the surface bulging out and back) changes the whole meniscus by much
more than its oscillation does, for the few frames the transient lasts: a burst of frame-to-frame change
(``change``, :func:`service.analysis.segment.frame_steps`). Frame n starts one when the mean change over
its ``transient`` frames, less the median change of the ``history`` frames before it (the baseline: noise,
or the ringing of the window before), exceeds both ``ratio`` times that baseline and ``floor`` times the
typical burst of the ejections found so far (the median of the last eight; spatter or a strong ringing
peak is a fraction of one). The ejection is the burst's first frame: the earliest frame, among the
transient frames before the strongest start, whose change reaches 0.3 of the burst's highest. None is
taken within ``refractory`` frames of the last (the transient and the ringing it starts).

What happens after the ejection is not consulted beyond the transient, so a settled meniscus, a heavily
or lightly damped one and 4 kHz modes look the same to it. Live runs it with ``lookahead`` = the transient
and two frames (a decision waits that long); offline with more, so that the strongest start within
``lookahead`` frames wins: the same code either way.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

#: The transient an ejection shows, s: the droplet leaving and the surface's bulge (0.25 ms simulated).
TRANSIENT_S = 0.3e-3
#: Frames before a start whose median change is its baseline, s.
HISTORY_S = 2e-3
#: No second ejection this soon after one, s (the printer's 250 Hz at most; its ringing is not a repeat).
REFRACTORY_S = 4e-3


#: A burst starts at its first frame whose change above the baseline reaches this share of its highest: the
#: bulge's first frame changes less than its fastest (one ejection in 50 at half, with the 4th frame the peak).
ONSET_FRACTION = 0.3


class EjectionDetector:
    """Ejection frames from consecutive batches of per-frame change; :meth:`push` returns those now decided."""

    def __init__(
        self,
        fps: float,
        lookahead: int | None = None,
        ratio: float = 2.0,
        floor: float = 0.3,
        refractory: int | None = None,
    ) -> None:
        self.transient = max(2, int(round(TRANSIENT_S * fps)))
        self.history = max(8, int(round(HISTORY_S * fps)))
        self.refractory = refractory if refractory is not None else max(self.transient + 1, int(REFRACTORY_S * fps))
        self.lookahead = max(self.transient + 2, lookahead if lookahead is not None else 0)
        self.ratio, self.floor = ratio, floor
        self._changes = np.empty(0)  # changes of frames [self._first, ...), NaN where missing
        self._first: int | None = None
        self._decided = 0  # frames before this index are decided
        self._last: int | None = None  # the last ejection
        self._start_checked = False
        self._bursts: deque[float] = deque(maxlen=8)

    @property
    def latency(self) -> int:
        """Frames that must follow a frame before :attr:`settled` passes it (whether an ejection starts there or
        in the transient before is known)."""
        return self.transient + self.lookahead - 2

    @property
    def settled(self) -> int:
        """No ejection found from now on lies before this frame (the stream's first frame before any)."""
        return self._decided - self.transient + 1 if self._first is not None else np.iinfo(np.int64).min

    def push(self, indices: np.ndarray, change: np.ndarray) -> list[int]:
        """Add frames ``indices`` (N,), increasing, with their change (N,); the ejections decided by them."""
        indices = np.asarray(indices, np.int64)
        if indices.size == 0:
            return []
        if self._first is None:
            self._first = self._decided = int(indices[0])
            self._start_checked = False
        end = self._first + self._changes.size
        grown = np.full(max(int(indices[-1]) + 1 - end, 0), np.nan)
        self._changes = np.concatenate([self._changes, grown])
        keep = indices >= self._first
        self._changes[indices[keep] - self._first] = np.asarray(change, np.float64)[keep]
        found = self._start(final=False)
        if not self._start_checked:
            return found
        return found + self._decide(self._first + self._changes.size - self.lookahead + 1)

    def finish(self) -> list[int]:
        """The stream ended: decide the frames still waiting for their look-ahead."""
        if self._first is None:
            return []
        return self._start(final=True) + self._decide(self._first + self._changes.size - self.transient)

    def _start(self, final: bool) -> list[int]:
        """Whether the stream starts with an ejection (a recording cut at one), once the ``history`` frames after
        the first transient are in (or the stream ended): its burst judged against them, since none came before."""
        if self._start_checked or (self._changes.size < 1 + self.transient + self.history and not final):
            return []
        self._start_checked = True
        burst, after = self._changes[1 : 1 + self.transient], self._changes[1 + self.transient :][: self.history]
        if not (np.isfinite(burst).any() and np.isfinite(after).sum() >= self.transient):
            return []
        level = np.nanmax(burst) - np.nanpercentile(after, 90)
        if not level > self.ratio * np.nanmedian(after):
            return []
        self._last = self._first
        self._bursts.append(float(level))
        return [self._first]

    def _decide(self, until: int) -> list[int]:
        """Decide frames [self._decided, until); keep the history the next decisions need."""
        lo = self._decided
        if until <= lo:
            return []
        c = self._changes
        at = lambda frame: frame - self._first
        pad = np.full(self.history, np.nan)
        ext = np.concatenate([pad, c, np.full(self.lookahead, np.nan)])  # ext[i + history] = c[i]
        span = np.arange(at(lo), at(until) + self.lookahead)
        with np.errstate(all="ignore"), _quiet():
            burst = np.nanmax(sliding_window_view(ext[self.history :], self.transient)[span], axis=1)
            past = sliding_window_view(ext, self.history)[span]
            base, top = np.nanmedian(past, axis=1), np.nanpercentile(past, 90, axis=1)
        level = np.nan_to_num(burst - top, nan=-np.inf)
        level[np.isfinite(past).sum(axis=1) < self.transient] = -np.inf  # too little history to judge against
        found = []
        for i in np.flatnonzero(np.arange(span.size) < at(until) - at(lo)):
            frame = lo + int(i)
            if self._last is not None and frame - self._last < self.refractory:
                continue
            if not (level[i] > self.ratio * base[i] and level[i] > self.floor * self._typical()):
                continue
            ahead = level[i : i + self.lookahead - self.transient + 1]
            if ahead.max() > level[i]:  # a stronger start follows within the look-ahead: decide there
                continue
            onset = self._onset(c, at(frame), top[i])
            self._last = self._first + onset
            self._bursts.append(float(level[i]))
            found.append(self._last)
        self._decided = until
        drop = max(0, at(until) - self.history - self.transient)
        self._changes, self._first = c[drop:], self._first + drop
        return found

    def _typical(self) -> float:
        """The median burst level of the recent ejections (0 before the first)."""
        return float(np.median(self._bursts)) if self._bursts else 0.0

    def _onset(self, c: np.ndarray, peak: int, top: float) -> int:
        """Position of the burst's first frame: the earliest of the ``transient`` frames up to ``peak`` whose
        change above ``top`` (the baseline's 90th percentile) reaches ONSET_FRACTION of the burst's highest."""
        lo = max(
            peak - self.transient + 1, 0, (self._last - self._first + self.refractory) if self._last is not None else 0
        )
        lo = min(lo, peak)
        span = np.nan_to_num(c[lo : peak + self.transient] - top, nan=0.0)
        return lo + int(np.argmax(span >= ONSET_FRACTION * span.max()))


class _quiet:
    """Silences numpy's warnings about all-NaN slices (a gap's frames: their statistics are NaN, as meant)."""

    def __enter__(self) -> None:
        import warnings

        self._catch = warnings.catch_warnings()
        self._catch.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc: object) -> None:
        self._catch.__exit__(*exc)


#: Offline looks this far ahead (s): the strongest start within it wins (live waits only the transient).
OFFLINE_LOOKAHEAD_S = 2e-3


def detect_ejections_streamed(change: np.ndarray, fps: float, offline: bool = True, batch: int = 256) -> np.ndarray:
    """The ejections of a whole series of per-frame change (N,) (NaN where unknown), fed to one
    :class:`EjectionDetector` ``batch`` frames at a time, with the offline look-ahead or the live one; (E,) int64."""
    detector = EjectionDetector(fps, lookahead=int(round(OFFLINE_LOOKAHEAD_S * fps)) if offline else None)
    found: list[int] = []
    for lo in range(0, len(change), batch):
        found += detector.push(np.arange(lo, min(lo + batch, len(change))), change[lo : lo + batch])
    return np.asarray(found + detector.finish(), np.int64)
