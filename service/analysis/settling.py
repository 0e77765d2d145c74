"""Settling metrics of a fitted window: when the oscillation falls under tolerance, what is left at the next ejection.

The fitted oscillation ``sum_k A_k exp(-g_k t) cos(2 pi f_k t + phi_k)`` (Eq. 1, t from the window
start) never exceeds its envelope ``E(t) = sum_k |A_k| exp(-g_k t)``; the metrics use ``E``, so a
window declared settled is settled whatever the phases. ``E`` never increases (``g_k >= 0``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import brentq

#: Settling later than this (s, ~3e9 years) is reported as never.
_LONGEST_S = 1e17


def envelope(t: ArrayLike, amplitudes: ArrayLike, decays: ArrayLike) -> np.ndarray:
    """E(t) = sum_k |A_k| exp(-g_k t) in mm.

    Parameters
    ----------
    t : array of shape (N,), s since the window start (>= 0).
    amplitudes : array of shape (M,), mm.
    decays : array of shape (M,), 1/s (>= 0).

    Returns
    -------
    ndarray of shape (N,), mm.
    """
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    amplitudes = np.abs(np.asarray(amplitudes, dtype=np.float64)).reshape(-1)
    decays = np.asarray(decays, dtype=np.float64).reshape(-1)
    with np.errstate(under="ignore", over="ignore"):  # a sum past the float range is inf: above any tolerance
        return (amplitudes * np.exp(-np.outer(t, decays))).sum(axis=1)


def tolerance(amplitudes: ArrayLike, fraction: float, floor_mm: float) -> float:
    """max(fraction * E(0), floor_mm): the band the envelope must stay in (mm); the fraction is taken of each term
    before they are summed, so that amplitudes summing past the float range still give a finite band."""
    with np.errstate(over="ignore"):
        return max(float((fraction * np.abs(np.asarray(amplitudes, dtype=np.float64))).sum()), floor_mm)


def _log_sum_exp(x: Sequence[float]) -> float:
    """log(sum(exp(x))) of a few values (M,) with a finite largest one, without leaving the float range; in plain
    floats: Brent calls it 10-40 times per window, where numpy's per-call overhead was most of a window's settling."""
    top = max(x)
    return float(top + math.log(math.fsum(math.exp(v - top) for v in x)))


def settling_time(amplitudes: ArrayLike, decays: ArrayLike, tol_mm: float) -> float:
    """First time (s) after which E(t) <= tol_mm for good; 0 if it starts there, inf if it never gets there.

    E is a sum of decaying exponentials, so it is monotone and the crossing is unique: closed form
    for one damped mode, Brent's method otherwise, bracketed by the times each term alone needs to
    fall under its share of the tolerance and by the slowest-decaying bound. Those can span hundreds of
    decades (a decay rate of 1e-176 /s next to 1e3 /s), so the root is sought in log t; E is compared
    with the tolerance in logs, so amplitudes over the tolerance by more than the float range (1e300
    against 1e-10) count exactly too. Undamped modes (g = 0) stay for ever, and so does anything
    needing longer than ``_LONGEST_S`` (bounds that overflow to inf, such as log(20) / 1e-323 /s, are
    beyond it).
    """
    amplitudes = np.abs(np.asarray(amplitudes, dtype=np.float64)).reshape(-1)
    decays = np.asarray(decays, dtype=np.float64).reshape(-1)
    damped = decays > 0
    with np.errstate(over="ignore"):  # a sum past the float range is inf: above any tolerance, as it should be
        if amplitudes.sum() <= tol_mm:
            return 0.0
        budget = tol_mm - amplitudes[~damped].sum()  # what the damped terms may still contribute
    if budget <= 0:
        return float("inf")
    a, g = amplitudes[damped], decays[damped]
    with np.errstate(divide="ignore", over="ignore"):  # log(0): a term without amplitude; x / 5e-324 s: inf
        log_a, log_budget = np.log(a), np.log(budget)
        reach = np.maximum(log_a + np.log(a.size) - log_budget, 0.0) / g  # each term under budget / M
        # E(t) >= sum(a) exp(-max(g) t), so E stays above the budget until ``low``
        low = float((_log_sum_exp(log_a.tolist()) - log_budget) / g.max())
    if a.size == 1:
        return float(reach[0]) if reach[0] <= _LONGEST_S else float("inf")

    terms = list(zip(log_a.tolist(), g.tolist()))

    def excess(t: float) -> float:
        """log E(t) over the budget's, the budget's last 1e-12 counted as rounding (Brent calls this ~10-40 times)."""
        return _log_sum_exp([log_ak - g_k * t for log_ak, g_k in terms]) - log_budget - 1e-12

    # every term is under its share by ``high``: the crossing is between, found in log t (no loss of
    # precision at any scale)
    high = min(float(reach.max()), _LONGEST_S)
    if excess(high) > 0:
        return float("inf")
    if low <= 0 or high <= low or excess(low) <= 0:  # the bound is the root (equal decay rates, or rounding)
        return float(max(low, 0.0))
    return float(np.exp(brentq(lambda u: excess(np.exp(u)), np.log(low), np.log(high), xtol=1e-12, rtol=1e-12)))


def damping_ratio(frequency_hz: ArrayLike, decay_per_s: ArrayLike) -> np.ndarray:
    """zeta = g / sqrt(g^2 + w^2), w = 2 pi f: the mode as the free response of x'' + 2 zeta w0 x' + w0^2 x = 0.

    0 for an undamped mode, 1 for a non-oscillating (critically or over-damped) one.
    """
    g = np.asarray(decay_per_s, dtype=np.float64)
    w0 = np.hypot(g, 2.0 * np.pi * np.asarray(frequency_hz, dtype=np.float64))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(w0 > 0, g / w0, 1.0)


def quality_factor(frequency_hz: ArrayLike, decay_per_s: ArrayLike) -> np.ndarray:
    """Q = 1 / (2 zeta) = w0 / (2 g); inf for an undamped mode.

    (harminv reports pi f / g instead, the same to first order in zeta.)
    """
    with np.errstate(divide="ignore"):
        return 0.5 / damping_ratio(frequency_hz, decay_per_s)


@dataclass(frozen=True)
class Settling:
    """Settling of one window of duration ``duration_s`` (the next ejection, when the window ends at one)."""

    time_s: float | None  # None: still above tolerance at the window's end
    settled: bool
    residual_amplitude_mm: float  # E(duration_s)
    tolerance_mm: float


def settle(amplitudes: ArrayLike, decays: ArrayLike, duration_s: float, fraction: float, floor_mm: float) -> Settling:
    """Settling time, settled-before-the-window-ends and residual envelope for modes (A_k mm, g_k 1/s)."""
    tol = tolerance(amplitudes, fraction, floor_mm)
    t_s = settling_time(amplitudes, decays, tol)
    residual = float(envelope(duration_s, amplitudes, decays)[0])
    settled = bool(t_s <= duration_s)
    return Settling(t_s if settled else None, settled, residual, tol)
