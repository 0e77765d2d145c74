"""The regularised nearest-neighbour fit (Price et al. 2022, Sec. 3.2 (a)): one window's centre
displacement as a decaying sinusoid through the frames' nearest-neighbour candidates.

Each frame i (time t_i) has k candidates D_ij(0) (its k nearest renders). The window's motion is

    f(t) = alpha exp(-beta t) sin(delta t - eps) + zeta

minimising || (min_j |D_ij - f(t_i)|)_i ||_2: every frame may pick whichever candidate lies on one
smooth damped oscillation, which rejects the single-frame mismatches a per-frame nearest neighbour
makes. The objective is not smooth (the min), so it is searched globally by differential evolution
(scipy), vectorised over the population; the paper needed hours, this takes well under a second per
190-frame window. Frequency ``delta / 2 pi``, decay rate ``beta``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import differential_evolution

from service.errors import MeniscopeError

#: Differential evolution: population per parameter, generations at most, relative tolerance.
POPSIZE, MAXITER, TOL = 20, 300, 1e-7
#: Frequencies searched: from half a cycle per window to this fraction of the frame rate (Nyquist 0.5).
MAX_CYCLES_PER_FRAME = 0.45
#: Decay rates searched: up to this many e-folds per window.
MAX_EFOLDS = 20.0


@dataclass(frozen=True)
class RegularisedFit:
    """The damped sinusoid through one window's candidates, and each frame's chosen candidate.

    ``frequency_hz``, ``decay_rate_per_s``, ``amplitude_mm`` (alpha >= 0), ``phase_rad`` (eps),
    ``offset_mm`` (zeta); ``centre`` (n,): per frame the candidate nearest the curve (mm); ``chosen``
    (n,): its column; ``rms_mm``: the objective over sqrt(n).
    """

    frequency_hz: float
    decay_rate_per_s: float
    amplitude_mm: float
    phase_rad: float
    offset_mm: float
    centre: np.ndarray
    chosen: np.ndarray
    rms_mm: float

    def curve(self, t: np.ndarray) -> np.ndarray:
        """f(t) in mm at times t (s) from the window's start."""
        return damped_sine(
            t, self.amplitude_mm, self.decay_rate_per_s, 2 * np.pi * self.frequency_hz, self.phase_rad, self.offset_mm
        )


def damped_sine(t: np.ndarray, alpha, beta, delta, eps, zeta) -> np.ndarray:
    """f(t) = alpha exp(-beta t) sin(delta t - eps) + zeta; parameters broadcast against t."""
    return alpha * np.exp(-beta * t) * np.sin(delta * t - eps) + zeta


def _spectral_start(nearest: np.ndarray, fps: float, bounds: list[tuple[float, float]]) -> np.ndarray:
    """A starting member for the search from the nearest candidates alone: offset their median, frequency
    the peak of their spectrum (zero-padded), amplitude from their spread, no decay, the phase of the peak."""
    n = len(nearest)
    zeta = float(np.median(nearest))
    pad = 8 * n
    spectrum = np.fft.rfft((nearest - zeta) * np.hanning(n), pad)
    freqs = np.fft.rfftfreq(pad, 1.0 / fps)
    usable = (2 * np.pi * freqs >= bounds[2][0]) & (2 * np.pi * freqs <= bounds[2][1])
    peak = np.flatnonzero(usable)[np.abs(spectrum[usable]).argmax()]
    x0 = np.array(
        [
            np.sqrt(2) * nearest.std(),
            0.0,
            2 * np.pi * freqs[peak],
            (-np.angle(spectrum[peak]) - np.pi / 2) % (2 * np.pi),
            zeta,
        ]
    )
    lower, upper = np.array(bounds).T
    inset = 1e-6 * (upper - lower)  # strictly inside: DE rescales x0 to [0, 1] and rounding may leave a bound
    return np.clip(x0, lower + inset, upper - inset)


def choose_candidates(candidates: np.ndarray, fps: float, seed: int = 0) -> RegularisedFit:
    """The regularised method on one window: the damped sinusoid through ``candidates`` (n, k) of D(0) in mm for n
    consecutive frames at ``fps``, and the candidate it passes nearest per frame."""
    c = np.asarray(candidates, np.float64)
    if c.ndim != 2 or c.shape[0] < 4 or c.shape[1] < 1:
        raise MeniscopeError("candidates", f"need (frames >= 4, k >= 1), got shape {c.shape}")
    if not np.all(np.isfinite(c)) or not (np.isfinite(fps) and fps > 0):
        raise MeniscopeError("candidates", "candidates and fps must be finite (fps > 0)")
    n = c.shape[0]
    t = np.arange(n) / fps
    duration = n / fps
    lo, hi = float(c.min()), float(c.max())
    span = max(hi - lo, 1e-6 * max(abs(lo), abs(hi), 1e-9))  # a width well above float64 rounding
    bounds = [
        (0.0, span),  # alpha
        (0.0, MAX_EFOLDS / duration),  # beta
        (np.pi / duration, 2 * np.pi * MAX_CYCLES_PER_FRAME * fps),  # delta
        (0.0, 2 * np.pi),  # eps
        (lo, lo + span),
    ]  # zeta (never a zero-width range: DE scales by it)

    def objective(x: np.ndarray) -> np.ndarray:
        x = x.reshape(5, -1)  # (5, S) candidates of the population
        f = damped_sine(t, *(v[:, None] for v in x))  # (S, n)
        gap = np.abs(c[None, :, :] - f[:, :, None]).min(axis=2)  # (S, n)
        return np.sqrt((gap * gap).sum(axis=1))  # (S,)

    result = differential_evolution(
        objective,
        bounds,
        popsize=POPSIZE,
        maxiter=MAXITER,
        tol=TOL,
        seed=seed,
        vectorized=True,
        updating="deferred",
        polish=False,
        init="sobol",
        x0=_spectral_start(c[:, 0], fps, bounds),
    )
    alpha, beta, delta, eps, zeta = result.x
    chosen = np.abs(c - damped_sine(t, *result.x)[:, None]).argmin(axis=1)
    return RegularisedFit(
        frequency_hz=delta / (2 * np.pi),
        decay_rate_per_s=beta,
        amplitude_mm=alpha,
        phase_rad=eps % (2 * np.pi),
        offset_mm=zeta,
        centre=c[np.arange(n), chosen],
        chosen=chosen,
        rms_mm=float(result.fun) / np.sqrt(n),
    )


def chosen_rows(
    candidates: np.ndarray, centre: np.ndarray, fps: float, seed: int = 0
) -> tuple[np.ndarray, RegularisedFit]:
    """One window's frames regularised: ``candidates`` (N, k) database rows per frame and ``centre`` the
    database's D(0, t) per row; per frame the row the window's damped sinusoid chose, and that fit."""
    fit = choose_candidates(centre[candidates], fps, seed=seed)
    return candidates[np.arange(len(candidates)), fit.chosen], fit
