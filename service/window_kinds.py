"""Kinds of window a recording can be drawn with, to test ejection detection on each (``simulate --kinds``).

Each kind changes one thing about the nominal window (:class:`service.simulate.WindowRanges`, the bulge of
:class:`service.simulate.Transient`, the ejection schedule or the camera): the meniscus settled, heavily or
lightly damped, 4 kHz modes, a faint ejection, the rate drifting +-5 %, a skipped ejection, spatter specks.
A recording of several kinds gives window k the kind ``kinds[k % len(kinds)]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from service.simulate import Transient, WindowRanges

NOMINAL = WindowRanges()


@dataclass(frozen=True)
class WindowKind:
    """One kind of window: its motion ranges, its ejection's bulge (mm), how its period departs from the
    schedule, and the spatter specks its frames show.

    ``drift``: the period is scaled by ``1 + drift * sin(2 pi k / 12)`` for window k (a rate drifting +-drift);
    ``skip_every``: every ``skip_every``-th window of the recording (k % skip_every == 1) runs two periods, its
    middle ejection skipped; ``spatter``: the probability that a frame shows 1-3 bright specks.
    """

    ranges: WindowRanges = NOMINAL
    bulge_mm: tuple[float, float] = Transient().bulge_mm
    drift: float = 0.0
    skip_every: int = 0
    spatter: float = 0.0

    def periods(self, k: int) -> float:
        """Window k's length in nominal ejection periods."""
        skipped = self.skip_every and k % self.skip_every == 1
        return (2.0 if skipped else 1.0) * (1.0 + self.drift * math.sin(2 * math.pi * k / 12))


KINDS: dict[str, WindowKind] = {
    "nominal": WindowKind(),
    # no oscillation left: a few micrometres, gone within a millisecond
    "settled": WindowKind(replace(NOMINAL, A1=(0.0, 0.002), A2=(0.0, 0.001), g1=(3000.0, 5000.0))),
    # 1-3 visible cycles
    "heavy": WindowKind(replace(NOMINAL, f1=(800.0, 2000.0), g1=(1500.0, 3000.0), g2_over_g1=(1.2, 1.5))),
    # still ringing at the next ejection (10 ms at 100 Hz: e^-0.1 .. e^-0.6 of the start)
    "light": WindowKind(replace(NOMINAL, g1=(10.0, 60.0), g2_over_g1=(1.2, 2.0))),
    # mode 1 at 4 kHz (mode 2 above it, under 0.35 fps at 19,000 frames/s), lightly damped
    "4khz": WindowKind(replace(NOMINAL, f1=(3800.0, 4200.0), f2_over_f1=(1.3, 1.55), g1=(50.0, 300.0))),
    # a droplet that barely moves the surface: the bulge about the oscillation's size
    "faint": WindowKind(bulge_mm=(0.02, 0.035)),
    "drift": WindowKind(drift=0.05),
    "skip": WindowKind(skip_every=3),
    "spatter": WindowKind(spatter=0.03),
}


def kinds_named(names: str) -> tuple[WindowKind, ...]:
    """The kinds of a comma-separated list of :data:`KINDS` names; ValueError naming an unknown one."""
    out = []
    for name in (n.strip() for n in names.split(",")):
        if name not in KINDS:
            raise ValueError(f"unknown window kind {name!r}: one of {', '.join(KINDS)}")
        out.append(KINDS[name])
    return tuple(out)


def spatter(frames: np.ndarray, probability: float, top: float, rng: np.random.Generator) -> None:
    """Specks of molten spatter, in place: each frame (N, H, W) shows with ``probability`` 1-3 bright discs of
    radius 1-2 px at random places (at 80-100 % of full scale ``top``)."""
    if probability <= 0:
        return
    n, h, w = frames.shape
    yy, xx = np.mgrid[:h, :w]
    for i in np.flatnonzero(rng.random(n) < probability):
        for _ in range(int(rng.integers(1, 4))):
            cy, cx, r = rng.uniform(0, h), rng.uniform(0, w), rng.uniform(1.0, 2.0)
            disc = (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r
            frames[i][disc] = np.asarray(rng.uniform(0.8, 1.0) * top).astype(frames.dtype)
