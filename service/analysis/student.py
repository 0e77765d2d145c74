"""Student's t quantile that every interval of a window takes (the fit's, the brightness polynomial's, a refined
window's pixel intervals, the harminv peer's): one definition, so that they cannot drift apart."""

from __future__ import annotations

import functools

from scipy.special import stdtrit


@functools.cache
def t_quantile(dof: int, confidence: float) -> float:
    """Student t's two-sided ``confidence`` quantile at ``dof`` degrees of freedom (``scipy.stats.t.ppf``'s value, from
    ``scipy.special`` without importing scipy.stats; cached: a window asks for a few values many times)."""
    return float(stdtrit(dof, 0.5 + confidence / 2))
