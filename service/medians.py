"""Medians of short 1-D series, the same bits as numpy's, without its per-call machinery.

``np.median`` and ``np.nanmedian`` cost 20-60 us a call on the few to a few hundred values the frame path takes
them of (a window's d and p, the detector's recent bursts and intervals; the latter through masked arrays), several
times per window: a good part of the main thread's Python in ``analyze`` (docs/benchmarks.md). Sorting and taking the
middle gives the same values: numpy's median of an even count is the mean of the two middle values, ``(a + b) / 2``,
of an odd one the middle value.
"""

from __future__ import annotations

import math

import numpy as np


def median(values: np.ndarray | list[float]) -> float:
    """``np.median`` of 1-D ``values``: NaN where any is NaN or there are none (numpy warns there; this does not)."""
    ordered = np.sort(np.asarray(values, np.float64))  # NaN sorts last
    if ordered.size == 0 or math.isnan(ordered[-1]):
        return math.nan
    return _middle(ordered)


def nanmedian(values: np.ndarray) -> float:
    """``np.nanmedian`` of 1-D ``values``: the median of those not NaN; NaN where all are (numpy warns there; this
    does not)."""
    values = np.asarray(values, np.float64)
    ordered = np.sort(values[~np.isnan(values)])
    return _middle(ordered) if ordered.size else math.nan


def _middle(ordered: np.ndarray) -> float:
    """The median of sorted values (at least one, none NaN). numpy's mean sums from +0.0, so a middle of -0.0 comes
    out +0.0; adding 0.0 first does the same and changes no other value."""
    half = ordered.size // 2
    if ordered.size % 2:
        return float(0.0 + ordered[half])
    return float((0.0 + ordered[half - 1] + ordered[half]) / 2)
