"""Ejections found from their own signature, as frames stream in: one detector for live and offline.

An ejection (the droplet leaving, the surface bulging out and back) changes the whole meniscus by much
more than its oscillation does, for the few frames the transient lasts: a burst of frame-to-frame change
(``change``, :func:`service.analysis.segment.frame_steps`). Frame n starts one when the mean change over
its ``transient`` frames, less the median change of the ``history`` frames before it (the baseline: noise,
or the ringing of the window before), exceeds both ``ratio`` times that baseline and ``floor`` times the
typical burst of the ejections found so far (the median of the last eight; spatter or a strong ringing
peak is a fraction of one). The ejection is the burst's first frame: the earliest frame, among the
transient frames before the strongest start, whose change reaches 0.2 of the burst's highest. None is
taken within ``refractory`` frames of the last (the transient and the ringing it starts). A stream's first
frame has no frames before it: it starts at an ejection when its first transient is a burst against the frames
after it, or, where the ejection's own ringing is as strong as its burst, when that transient reaches half the
first ejection found after it (frames wait for that decision, at most :data:`START_WAIT_S`).

Where ringing is as strong as an ejection's burst (a lightly damped meniscus, 4 kHz modes) the burst does not
stand ``ratio`` above it, but the bulge is a shape the ringing has not shown: each frame's ``novelty``
(:mod:`service.pipeline.measures`: its coarse picture's distance from the nearest of the frames 0.35-3 ms before;
ringing keeps returning to its last period's shapes) bursts at an ejection. There the recent ejection period (the
median interval between the ejections found) says where to look: in the stretch of +-10 % about a multiple of it
after the last ejection, the start where change and novelty stand out most together (the product of each one's
burst above its baseline's 90th percentile, in baseline medians; the novelty's over the bulge's rise, half the
transient) is the ejection, once that product passes :data:`STRETCH_SCORE` (a start that does waits for the
stretch's end). The rate is learned from the video, not assumed, and a skipped ejection or a rate drifting a few per cent
keeps it. The stream's first ejections into such ringing come before any period is known: the stream's first frames
wait (their change and novelty, at most :data:`PERIOD_WAIT_S`) until two intervals agree on one (the longest of which
each is about a multiple), and the stretches it then puts between, before and after the ejections found are judged as
above, narrowed to the held intervals' own scatter (and :data:`LOOK_BACK_MARGIN`), from :data:`LOOK_BACK_SCORE` on. No start in the stream's first ``history`` frames is judged by its burst (a baseline shorter than a slow
ringing's period misses its peaks), and a held one whose burst falls under ``floor`` times the held ones' median (the
floor those set later: ringing that beats passes ``ratio`` against its own quiet frames) is dropped; the stream's first
frame counts towards the period only where it fits it, or where a shorter period that it fits finds more ejections. A stretch's ejection starts at the first peak of that product before its highest (the ringing an
ejection starts can stand out more than its own first frames).

What happens after the ejection is not consulted beyond the transient, so a settled meniscus, a heavily
or lightly damped one and 4 kHz modes look the same to it. Live runs it with ``lookahead`` = the transient
and two frames (a decision waits that long); offline with more, so that the strongest start within
``lookahead`` frames wins: the same code either way.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numba import njit

from service.medians import median

#: The transient an ejection shows, s: the droplet leaving and the surface's bulge (0.25 ms simulated).
TRANSIENT_S = 0.3e-3
#: Frames before a start whose median change is its baseline, s.
HISTORY_S = 2e-3
#: No second ejection this soon after one, s (the printer's 250 Hz at most; its ringing is not a repeat).
REFRACTORY_S = 4e-3


#: A stream whose first transient is not plainly a burst against the frames after it (the ejection's ringing can
#: be as strong) starts at an ejection when its first transient's highest change reaches this share of the first
#: ejection found after it: decided then, or not at all once the stream has run this long without one (s).
START_FRACTION = 0.5
START_WAIT_S = 25e-3
#: The stream's first ejections are held (and its frames wait) until two intervals between them agree on a period, at
#: most this long (s); then the stretches the period puts between and before them are looked at (:data:`STRETCH_SCORE`).
PERIOD_WAIT_S = 80e-3

#: A burst starts at its first frame whose change above the baseline reaches this share of its highest: the
#: bulge's first frame changes less than its fastest (one ejection in 50 at half; at 0.3 an ejection into strong
#: ringing, its first frames 60 above the ringing and its 6th 220, was placed 5 frames late).
ONSET_FRACTION = 0.2


#: Where the recent ejection period puts the next ejection: within this share of the time since the last, up to
#: this many periods on (an ejection into a meniscus still ringing as hard as its burst stands out from that
#: ringing less than ``ratio``; there its novelty decides, :data:`STRETCH_SCORE`).
EXPECTED_SPREAD = 0.1
EXPECTED_PERIODS = 3

#: Novelty (:mod:`service.pipeline.measures`) compares a frame with the frames from just past the transient
#: (whose bulge would otherwise match its own first frames) to this far back (s): more than the slowest ringing's
#: period (500 Hz), so that ringing finds its last period's shapes there.
NOVELTY_SPAN_S = 3e-3
#: In an expected ejection's stretch, the ejection is the start where the change and the novelty stand out most
#: together (the product of how far each stands above its baseline, in baselines: the ringing's strongest change
#: repeats shapes, its newest shapes change little) once that product passes this.
STRETCH_SCORE = 0.5
#: The stream's first ejections, held until the period is known, measure it to a frame or two: the stretches looked
#: back at are as wide as the held intervals' own scatter about their multiples of it and this (frames, the scoring
#: tolerance), not EXPECTED_SPREAD of the period. Ringing passes a lower score within so few frames less often than
#: STRETCH_SCORE within the wider stretch (docs/ejections.md), so a looked-back stretch's start is taken from this
#: score on: an ejection buried in light ringing scores under STRETCH_SCORE, the ringing it starts above it.
LOOK_BACK_MARGIN = 2.0
LOOK_BACK_SCORE = 0.1


def novelty_lags(fps: float) -> tuple[int, int]:
    """The frames (nearest, farthest back) novelty compares each frame with, at ``fps`` frames per second."""
    near = max(2, int(round(TRANSIENT_S * fps))) + 1
    return near, max(near, int(round(NOVELTY_SPAN_S * fps)))


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
        self._start_wait = int(START_WAIT_S * fps)
        self._period_wait = int(PERIOD_WAIT_S * fps)
        self._changes = np.empty(0)  # changes of frames [self._first, ...), NaN where missing
        self._novelty = np.empty(0)  # their novelty, the same frames
        self._first: int | None = None
        self._decided = 0  # frames before this index are decided
        self._last: int | None = None  # the last ejection
        self._start_checked = False
        self._origin = 0  # the stream's first frame
        self._pending: float | None = None  # the first transient's highest change while its ejection is undecided
        self._bursts: deque[float] = deque(maxlen=8)
        self._intervals: deque[int] = deque(maxlen=8)  # frames between consecutive ejections found
        self._learning = True  # the stream's first ejections are held until a period is known
        self._held: list[int] = []
        # each held ejection found by its own burst: that burst's level (the floor's) and highest change (the start's)
        self._held_bursts: dict[int, tuple[float, float]] = {}
        self._start_highest: float | None = None  # the stream's first transient's, where its first ejection took it
        self._run: int | None = None  # the first of the unbroken run of starts that pass, up to the frame deciding

    @property
    def latency(self) -> int:
        """Frames that must follow a frame before :attr:`settled` passes it (whether an ejection starts there or
        in the transient before is known); more where a start in an expected ejection's stretch that scores above
        STRETCH_SCORE waits for the stretch's end (a tenth of the period after its middle)."""
        return self.transient + self.lookahead - 2

    @property
    def settled(self) -> int:
        """No ejection found from now on lies before this frame (the stream's first frame before any, and while
        whether it starts at one is undecided)."""
        if self._first is None:
            return np.iinfo(np.int64).min
        held = self._pending is not None or self._learning
        return self._origin if held else self._decided - self.transient + 1

    def push(self, indices: np.ndarray, change: np.ndarray, novelty: np.ndarray | None = None) -> list[int]:
        """Add frames ``indices`` (N,), increasing, with their change and novelty (N,) (NaN where unknown, as all
        of it is without ``novelty``); the ejections decided by them."""
        indices = np.asarray(indices, np.int64)
        if indices.size == 0:
            return []
        if self._first is None:
            self._first = self._decided = self._origin = int(indices[0])
            self._start_checked, self._learning = False, True
        end = self._first + self._changes.size
        grown = np.full(max(int(indices[-1]) + 1 - end, 0), np.nan)
        self._changes = np.concatenate([self._changes, grown])
        self._novelty = np.concatenate([self._novelty, grown])
        keep = indices >= self._first
        self._changes[indices[keep] - self._first] = np.asarray(change, np.float64)[keep]
        if novelty is not None:
            self._novelty[indices[keep] - self._first] = np.asarray(novelty, np.float64)[keep]
        found = self._start(final=False)
        if not self._start_checked:
            return found
        found += self._decide(self._first + self._changes.size - self.lookahead + 1)
        if self._pending is not None and self._decided - self._origin > self._start_wait:
            self._pending = None  # no ejection for long: the stream started inside a window
        return self._release(found, final=False)

    def finish(self) -> list[int]:
        """The stream ended: decide the frames still waiting for their look-ahead."""
        if self._first is None:
            return []
        found = self._start(final=True) + self._decide(self._first + self._changes.size - self.transient, final=True)
        self._pending = None
        return self._release(found, final=True)

    def _release(self, found: list[int], final: bool) -> list[int]:
        """The ejections ``found`` once the stream's period is known; before, they are held, and once it is (two
        intervals agree on one, the stream has run PERIOD_WAIT_S or ended) returned with those the period finds
        between and before them: a third or half of it where that finds one in every stretch it puts between them
        (a 4 kHz stream whose every other ejection does not stand out by its burst agrees on two periods)."""
        if not self._learning:
            return found
        self._held += found
        clear = self._clear(self._held)
        held = self._agreed(clear)
        if held is None and not (final or self._decided - self._origin > self._period_wait):
            return []
        self._learning = False
        held, self._held = held or clear, []
        self._held_bursts.clear()
        if len(held) < 3:
            return held
        # those looked back at are not bursts: the floor stays the clear bursts'
        unit = self._unit(np.diff(held))
        found = held + self._look_back(held, unit)
        # every other ejection buried in ringing, the held ones agree on two (or three) periods: a third or half of it
        # is the period where it finds an ejection in every stretch it puts between them
        for k in (3, 2) if unit is not None else ():
            sub = unit / k
            if sub < self.refractory:
                continue
            more = self._look_back(held, sub)
            between = sum(round((b - a) / sub) - 1 for a, b in zip(held, held[1:]))
            if 0 < between == sum(held[0] < f < held[-1] for f in more):
                found = held + more
                break
        if len(held) < len(clear):  # the first, off the period: kept where a shorter one fits it and finds an
            unit = self._unit(np.diff(clear))  # ejection in every stretch it puts between the others
            more = self._look_back(clear, unit) if unit is not None else []
            between = sum(round((b - a) / unit) - 1 for a, b in zip(clear[1:], clear[2:])) if unit is not None else 0
            found = clear + more if 0 < between == sum(clear[1] < f < clear[-1] for f in more) else found
        found = sorted(found)
        self._intervals.clear()
        self._intervals.extend(np.diff(found).tolist())
        self._last = found[-1]
        return found

    def _clear(self, held: list[int]) -> list[int]:
        """``held`` but those found by their own burst whose burst falls under ``floor`` times the median of those
        bursts (the floor that the recent ejections set later in the stream; before the first, ringing that beats
        passes ``ratio`` against its own quiet frames), and the stream's first frame where one of those took it and
        its transient falls under START_FRACTION of their median highest change."""
        own = np.array([self._held_bursts[f] for f in held if f in self._held_bursts]).reshape(-1, 2)
        if not own.size:
            return held
        weak, start = self.floor * np.median(own[:, 0]), START_FRACTION * np.median(own[:, 1])

        def clear(frame: int) -> bool:
            if frame in self._held_bursts:
                return self._held_bursts[frame][0] >= weak
            return frame != self._origin or self._start_highest is None or self._start_highest >= start

        return [f for f in held if clear(f)]

    def _agreed(self, held: list[int]) -> list[int] | None:
        """``held`` once two intervals between them agree on a period, None before. A first one within the stream's
        first ``history`` frames (judged against a short baseline or none: a stream started inside a window may
        ring harder at first than later) does not count towards the period, and stays only within EXPECTED_SPREAD of a
        period of where it puts one (not n times that: 37 frames into a 4 kHz window, two periods before, is no ejection)."""
        early = bool(held) and held[0] - self._origin < self.history
        rest = held[1:] if early else held
        unit = self._unit(np.diff(rest)) if len(rest) >= 3 else None
        if unit is None:
            return None
        n = round((held[1] - held[0]) / unit)
        fits = n >= 1 and abs(held[1] - held[0] - n * unit) <= EXPECTED_SPREAD * unit
        return held if not early or fits else rest

    def _look_back(self, held: list[int], period: float | None) -> list[int]:
        """The ejections in the stretches that ``period`` puts between the ``held`` ejections (each gap about a
        multiple of it) and before the first (back to the stream's start, up to EXPECTED_PERIODS), each as wide as the
        ``held`` intervals' scatter about their multiples of ``period`` and LOOK_BACK_MARGIN (at most EXPECTED_SPREAD of
        it): the start where change and novelty stand out most together, where it passes LOOK_BACK_SCORE. The start
        the wider stretch (EXPECTED_SPREAD) would take stays where it lies in the narrow one: its first peak is sought
        from the ringing an ejection starts, which the narrow stretch can cut off."""
        if period is None:
            return []
        intervals = np.diff(held)
        multiples = np.maximum(np.round(intervals / period), 1)
        scatter = float(np.max(np.abs(intervals - multiples * period) / multiples))
        wide = max(2.0, EXPECTED_SPREAD * period)
        narrow = min(wide, scatter + LOOK_BACK_MARGIN)
        stretches = [
            (a + j * (b - a) / n, 1)
            for a, b in zip(held, held[1:])
            for n in [int(round((b - a) / period))]
            for j in range(1, n)
        ]
        if held[0] != self._origin:
            stretches += [(held[0] - k * period, k) for k in range(1, EXPECTED_PERIODS + 1)]
        # and after the last, where already decided (held, no stretch was looked at)
        stretches += [(held[-1] + k * period, k) for k in range(1, EXPECTED_PERIODS + 1)]
        lo, hi = self._origin + self.history, self._first + self._changes.size - self.transient
        found: list[int] = []
        for centre, k in stretches:
            if centre >= self._decided:
                continue
            frames = np.arange(
                max(int(np.ceil(centre - k * wide)), lo), min(int(np.floor(centre + k * wide)), hi - 1) + 1
            )
            inside = np.abs(frames - centre) <= k * narrow
            if not inside.any():
                continue
            positions = frames - self._first
            _, level, base, _ = self._levels(positions)
            score = self._scores(level, base, positions)
            best = int(frames[self._first_peak(score, int(np.argmax(score)))])
            if abs(best - centre) > k * narrow:
                score, frames = score[inside], frames[inside]
                best = int(frames[self._first_peak(score, int(np.argmax(score)))])
            top = score[np.abs(frames - centre) <= k * narrow].max()
            if top > LOOK_BACK_SCORE and min(abs(best - f) for f in held + found) >= self.refractory:
                found.append(best)
        return found

    def _unit(self, intervals: np.ndarray) -> float | None:
        """The longest period (at least the refractory time) of which each of ``intervals`` is about a multiple
        (within EXPECTED_SPREAD of that multiple), from the shortest one over up to EXPECTED_PERIODS: the
        intervals' median in it; None where there is none."""
        for k in range(1, EXPECTED_PERIODS + 1):
            unit = float(np.min(intervals)) / k
            if unit < self.refractory:
                break
            n = np.round(intervals / unit)  # at least 1: the unit is at most the shortest
            if np.all(np.abs(intervals - n * unit) <= EXPECTED_SPREAD * n * unit):
                return median(intervals / n)
        return None

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
            self._pending = float(np.nanmax(burst))  # decided by the first ejection found after it
            return []
        self._last = self._first
        self._bursts.append(float(level))
        self._held_bursts[self._first] = (float(level), float(np.nanmax(burst)))
        return [self._first]

    def _decide(self, until: int, final: bool = False) -> list[int]:
        """Decide frames [self._decided, until) (or fewer, where an expected ejection's stretch is not all in
        unless ``final``); keep the history the next decisions need."""
        lo = self._decided
        if until <= lo:
            return []
        c = self._changes
        at = lambda frame: frame - self._first
        span = np.arange(at(lo), max(at(until) + self.lookahead, c.size))
        burst, level, base, top = self._levels(span)
        levels, bases = level.tolist(), base.tolist()  # floats: the loop below looks at every frame
        found = []
        typical = self.floor * self._typical()
        count = max(0, min(span.size, at(until) - at(lo)))
        stretch_of = self._stretches(lo, count)
        stretch_first = stretch_of[:, 0].tolist()  # ints: looked at every frame
        ratio, refractory = self.ratio, self.refractory
        scored: tuple[int, int, np.ndarray] | None = None  # a stretch's first and last position, its starts' scores
        for i in range(count):
            frame = lo + i
            if self._last is not None and frame - self._last < refractory:
                self._run = None
                continue
            if levels[i] > ratio * bases[i] and levels[i] > typical:
                self._run = frame if self._run is None else self._run
                ahead = level[i : i + self.lookahead - self.transient + 1]
                stronger = span[i] + int(np.argmax(ahead))
                if ahead.max() > level[i] and not self._newer(span[i], stronger):
                    continue  # a stronger start follows within the look-ahead, showing no older shape: decide there
                onset = self._onset(at(frame), top[i], at(self._run), self.ratio * bases[i])
            elif stretch_first[i] >= 0 and levels[i] > 0:  # where the rate puts the next ejection
                self._run = None
                a, b = stretch_first[i], int(stretch_of[i, 1])
                if scored is None or scored[:2] != (a, b):  # the stretch's starts, as far as they are in
                    z = min(b, span.size - 1) + 1
                    scored = (a, b, self._scores(level[a:z], base[a:z], span[a:z]))
                score = scored[2]
                if not score[i - a] > STRETCH_SCORE:
                    continue
                if lo + b + self.transient > self._first + c.size:  # the stretch's last burst is not all in: wait
                    if final:  # cut by the stream's end: no telling its strongest start
                        continue
                    until = frame
                    break
                if i != a + int(np.argmax(score)):
                    continue
                onset = at(lo + a + self._first_peak(score, i - a))
            else:
                self._run = None
                continue
            if self._last is not None:
                self._intervals.append(self._first + onset - self._last)
            self._last = self._first + onset
            self._bursts.append(float(level[i]))
            if self._learning and self._run is not None:  # found by its own burst
                self._held_bursts[self._last] = (float(level[i]), float(burst[i]))
            typical = self.floor * self._typical()
            stretch_of = self._stretches(lo, count)
            stretch_first = stretch_of[:, 0].tolist()
            if self._pending is not None:  # the stream's start judged against its first ejection
                starts = self._last - self._origin >= self.refractory and self._pending >= START_FRACTION * burst[i]
                if starts:
                    self._start_highest = self._pending
                    found.append(self._origin)
                    self._intervals.append(self._last - self._origin)
                self._pending = None
            found.append(self._last)
        self._decided = until
        drop = 0 if self._learning else max(0, at(until) - self.history - self.transient)
        self._changes, self._first = c[drop:], self._first + drop
        self._novelty = self._novelty[drop:]
        return found

    def _levels(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For starts at ``positions`` (in the kept frames): the highest change over the transient, how far it
        stands above the baseline's 90th percentile (-inf where the baseline is too short to judge against), the
        baseline's median and its 90th percentile."""
        burst, base, top, known = _window_levels(self._padded(self._changes), positions, self.history, self.transient)
        level = _nan_to(burst - top, nan=-np.inf)
        level[known < self.transient] = -np.inf  # too little history to judge against
        # nor in the stream's first ``history``: a baseline shorter than a slow ringing's period misses its peaks
        level[positions + self._first < self._origin + self.history] = -np.inf
        return burst, level, base, top

    def _padded(self, kept: np.ndarray) -> np.ndarray:
        """A kept per-frame series with ``history`` NaN before it and ``lookahead`` after: ext[i + history] is
        frame i's value, so that every start has a whole baseline and transient window."""
        return np.concatenate([np.full(self.history, np.nan), kept, np.full(self.lookahead, np.nan)])

    def _stretches(self, lo: int, count: int) -> np.ndarray:
        """For frames ``lo .. lo + count - 1``: the first and last frame (from ``lo``) of the stretch about a
        multiple (up to EXPECTED_PERIODS) of the recent ejection period (the median of the last intervals) after
        the last ejection that each lies in, +-``EXPECTED_SPREAD`` of that time; (count, 2), -1 where none (or
        too few ejections are known)."""
        out = np.full((count, 2), -1, np.int64)
        if self._last is None or not self._intervals or self._learning:
            return out
        period = median(self._intervals)
        for k in range(1, EXPECTED_PERIODS + 1):
            centre, spread = self._last + k * period, max(2.0, EXPECTED_SPREAD * k * period)
            a, b = int(np.ceil(centre - spread)) - lo, int(np.floor(centre + spread)) - lo
            out[max(a, 0) : max(b + 1, 0)] = (max(a, 0), b)
        return out

    def _scores(self, level: np.ndarray, base: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """How much the starts at ``positions`` (in the kept frames) stand out in change and novelty together:
        the product of each one's burst above its baseline's 90th percentile, in baseline medians (0 where either
        is not above it; ``level`` and ``base`` are the change's, over the transient; the novelty's over its
        first half, while the bulge grows, so that the start nearest the bulge's first frame scores highest)."""
        rise = max(1, (self.transient + 1) // 2)
        burst, novel_base, novel_top, known = _window_levels(self._padded(self._novelty), positions, self.history, rise)
        with np.errstate(all="ignore"):
            novel = np.where(known >= self.transient, (burst - novel_top) / novel_base, np.nan)
            change = level / base
        return _nan_to(np.clip(change, 0, None) * np.clip(novel, 0, None), nan=0.0, posinf=0.0)

    def _first_peak(self, score: np.ndarray, best: int) -> int:
        """Where, among a stretch's starts ``score``, the ejection that its highest ``best`` belongs to starts: the
        first of the transient's starts up to ``best`` that stands above both its neighbours and reaches
        ONSET_FRACTION of the highest (the ringing an ejection starts can stand out more than the ejection's own
        first frames: a 4 kHz mode on a Blender recording), else ``best``."""
        lo = max(0, best - self.transient + 1)
        s = score[lo : best + 1]
        peak = (s >= ONSET_FRACTION * s[-1]) & (s > np.append(s[1:], -np.inf)) & (s > np.append(-np.inf, s[:-1]))
        peak[-1] = True
        return lo + int(np.argmax(peak))

    def _newer(self, start: int, other: int) -> bool:
        """Whether the start at kept position ``start`` shows a newer shape than the one at ``other`` (the highest
        novelty over each one's transient): the ringing an ejection starts can change the frame more than the
        bulge did (a 4 kHz mode), never show as new a shape. False where novelty is unknown."""
        n, t = self._novelty, self.transient  # fmax: nanmax's values, NaN where all are, without its warning
        return bool(np.fmax.reduce(n[start : start + t]) > np.fmax.reduce(n[other : other + t]))

    def _typical(self) -> float:
        """The median burst level of the recent ejections (0 before the first)."""
        return median(self._bursts) if self._bursts else 0.0

    def _onset(self, peak: int, top: float, run: int, clear: float) -> int:
        """Position of the burst's first frame: the earliest of the frames from the ``transient`` before ``peak``, or
        from ``run`` (the first of the unbroken run of passing starts it ends: the ringing an ejection starts can
        change the frame more than its bulge, and the look-ahead then decides at the ringing), whose change above
        ``top`` (the baseline's 90th percentile) reaches ONSET_FRACTION of the burst's highest, or ``clear`` (as far above
        it as a burst must stand: a faint droplet's first frames can change the frame less than a fifth of the bulge),
        or which starts two frames that each change the frame ONSET_FRACTION of ``clear`` above ``top`` and show a
        new shape (novelty ``ratio`` novelty medians above its baseline's 90th percentile: a faint droplet's first
        frames in high noise; a speck of spatter is one frame)."""
        lo = max(
            min(peak - self.transient + 1, run),
            0,
            (self._last - self._first + self.refractory) if self._last is not None else 0,
        )
        lo = min(lo, peak)
        span = _nan_to(self._changes[lo : peak + self.transient] - top, nan=0.0)
        onset = span >= min(ONSET_FRACTION * span.max(), clear)
        _, novel_base, novel_top, _ = _window_levels(self._padded(self._novelty), np.array([peak]), self.history, 1)
        with np.errstate(invalid="ignore"):
            new = (span >= ONSET_FRACTION * clear) & (
                self._novelty[lo : peak + self.transient] >= novel_top[0] + self.ratio * novel_base[0]
            )
        onset[:-1] |= new[:-1] & new[1:]
        return lo + int(np.argmax(onset))


#: float64's largest finite value, where ``np.nan_to_num`` puts infinities.
_LARGEST = float(np.finfo(np.float64).max)


def _nan_to(values: np.ndarray, nan: float, posinf: float = _LARGEST) -> np.ndarray:
    """``np.nan_to_num(values, nan=nan, posinf=posinf)`` (-inf to float64's lowest) of a float64 array made for the
    call, in place: without numpy's per-call type lookups, most of what it cost the live detector's small batches."""
    nans, high, low = np.isnan(values), values == np.inf, values == -np.inf
    values[nans] = nan
    values[high] = posinf
    values[low] = -_LARGEST
    return values


@njit(cache=True, nogil=True)
def _window_levels(ext, positions, history, width):  # type: ignore[no-untyped-def]
    """For each start ``p`` of ``positions``: the highest finite value of ``ext[history + p : history + p + width]``
    (the burst), the median and 90th percentile of the finite values of ``ext[p : p + history]`` (the baseline
    before it; numpy's linear interpolation) and how many those are; NaN where a window holds none.

    Compiled, one start at a time: numpy's version (a sort of every baseline row, ``take_along_axis``, ``nanmax``
    and a warnings filter for the all-NaN rows) paid its per-call overhead on each of live's small batches
    (docs/benchmarks.md). A start one after the last keeps its sorted baseline, less the value that left it and
    with the one that entered (the same values in the same order as sorting it afresh, so the same quantiles);
    any other is sorted afresh."""
    count = positions.size
    burst = np.full(count, np.nan)
    median = np.full(count, np.nan)
    p90 = np.full(count, np.nan)
    known = np.zeros(count, np.int64)
    window = np.empty(history)
    n, last = 0, -2  # window[:n]: the finite values of the baseline of start ``last``, sorted
    for i in range(count):
        p = positions[i]
        for k in range(history + p, history + p + width):
            v = ext[k]
            if not np.isnan(v) and (np.isnan(burst[i]) or v > burst[i]):
                burst[i] = v
        if p == last + 1:
            n = _slide(window, n, ext[p - 1], ext[p + history - 1])
        else:
            n = 0
            for k in range(p, p + history):
                if not np.isnan(ext[k]):
                    window[n] = ext[k]
                    n += 1
            window[:n].sort()
        last = p
        known[i] = n
        if n == 0:
            continue
        ordered = window[:n]
        median[i], p90[i] = _quantile(ordered, 0.5), _quantile(ordered, 0.9)
    return burst, median, p90, known


@njit(cache=True, nogil=True)
def _slide(window, n, leaving, entering):  # type: ignore[no-untyped-def]
    """Sorted ``window[:n]`` less one value equal to ``leaving`` and with ``entering`` in its place in the order
    (either skipped where NaN); returns the new count. ``window`` has room for the entering value."""
    if not np.isnan(leaving):
        at = np.searchsorted(window[:n], leaving)
        window[at : n - 1] = window[at + 1 : n].copy()
        n -= 1
    if not np.isnan(entering):
        at = np.searchsorted(window[:n], entering)
        window[at + 1 : n + 1] = window[at:n].copy()
        window[at] = entering
        n += 1
    return n


@njit(cache=True, nogil=True)
def _quantile(ordered, q):  # type: ignore[no-untyped-def]
    """The ``q`` quantile of sorted values (at least one), by numpy's linear interpolation."""
    position = q * (ordered.size - 1)
    lo = int(np.floor(position))
    hi = min(lo + 1, ordered.size - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (position - lo)


#: Offline looks this far ahead (s): the strongest start within it wins (live waits only the transient).
OFFLINE_LOOKAHEAD_S = 2e-3


def detect_ejections_streamed(
    change: np.ndarray, fps: float, offline: bool = True, batch: int = 256, novelty: np.ndarray | None = None
) -> np.ndarray:
    """The ejections of a whole series of per-frame change and novelty (N,) (NaN where unknown), fed to one
    :class:`EjectionDetector` ``batch`` frames at a time, with the offline look-ahead or the live one; (E,) int64."""
    detector = EjectionDetector(fps, lookahead=int(round(OFFLINE_LOOKAHEAD_S * fps)) if offline else None)
    found: list[int] = []
    for lo in range(0, len(change), batch):
        part = slice(lo, min(lo + batch, len(change)))
        found += detector.push(
            np.arange(part.start, part.stop), change[part], None if novelty is None else novelty[part]
        )
    return np.asarray(found + detector.finish(), np.int64)
