"""The regularised nearest-neighbour fit (Price et al. 2022, Sec. 3.2 (a)): one window's centre
displacement as damped membrane modes through the frames' nearest-neighbour candidates.

Each frame i (time t_i from the window's first frame) has k candidates D_ij(0), the centre displacements
of its k nearest renders, found at image distances e_ij. The window's motion is Eq. 1 at the centre:

    f(t) = zeta + sum_m A_m exp(-g_m t) cos(2 pi f_m t + phi_m),   m = 1, 2

with mode 2's frequency near l2 / l1 = 2.295 times mode 1's (the Bessel roots that shape Eq. 1's modes)
and decaying at least as fast, so mode 1 is the dominant, longest-lasting one. Three well-posed steps
(the paper's single objective, min_j |D_ij - f(t_i)|, rewarded curves that zig-zag through stray
candidates):

1. per frame a robust pick: the weighted median of its candidates, weights (e_i0 / e_ij)^2, so the
   nearest renders count most and one stray candidate cannot move it;
2. the nonlinear parameters (f1, g1, f2 / f1, g2 / g1) by differential evolution inside physical bounds,
   the linear ones (zeta, each mode's cosine and sine amplitude) solved exactly for every member by
   ridge least squares (variable projection); the objective is the Huber loss of the residuals, so
   frames whose pick is wrong weigh less;
3. per frame the candidate nearest that curve, and a last robust fit through those (soft-L1 loss).

About 0.1-0.3 s per 190-frame window on one core.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import differential_evolution, least_squares

from service.errors import MeniscopeError
from service.physics import L1, L2, damped_mode

#: Differential evolution: population per parameter, generations at most, relative tolerance.
POPSIZE, MAXITER, TOL = 12, 150, 1e-6
#: Highest frequency searched for mode 2, as a fraction of the frame rate (Nyquist is 0.5).
MAX_CYCLES_PER_FRAME = 0.45
#: Decay rates searched: up to this many e-folds per window.
MAX_EFOLDS = 20.0
#: Mode 2 / mode 1 frequency ratio: the Bessel roots' l2 / l1 = 2.295, give or take this fraction.
RATIO_TOLERANCE = 0.15
#: Mode 2 / mode 1 decay-rate ratio: at least 1 (mode 1 dominant), at most this.
MAX_DECAY_RATIO = 6.0
#: Huber and soft-L1 scale: this fraction of the picks' 5-95 % spread.
ROBUST_FRACTION = 0.1
#: Times each member's curve re-picks per frame the candidate nearest it and is refitted through them.
ALTERNATIONS = 4
#: Offsets tried for the curve that re-picks candidates (the picks' own level can be biased).
SHIFTS = 41
#: Ridge weight on the linear amplitudes, relative to the frame count (keeps short windows well posed).
RIDGE = 1e-6


@dataclass(frozen=True)
class RegularisedFit:
    """The damped modes through one window's candidates, and each frame's chosen candidate.

    ``modes`` (2, 4): per mode frequency (Hz), decay rate (1/s), amplitude (mm, >= 0), phase (rad) of
    A exp(-g t) cos(2 pi f t + phi), mode 1 (dominant) first; ``offset_mm``: zeta; ``centre`` (n,): per
    frame the candidate nearest the curve (mm); ``chosen`` (n,): its column; ``rms_mm``: RMS of
    ``centre`` about the curve.
    """

    modes: np.ndarray
    offset_mm: float
    centre: np.ndarray
    chosen: np.ndarray
    rms_mm: float

    @property
    def frequency_hz(self) -> float:
        return float(self.modes[0, 0])

    @property
    def decay_rate_per_s(self) -> float:
        return float(self.modes[0, 1])

    @property
    def amplitude_mm(self) -> float:
        return float(self.modes[0, 2])

    def curve(self, t: np.ndarray) -> np.ndarray:
        """f(t) in mm at times t (s) from the window's first frame."""
        t = np.asarray(t, np.float64)[..., None]
        f, g, a, phi = self.modes.T
        return self.offset_mm + damped_mode(t, a, g, f, phi).sum(axis=-1)


def weighted_median(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Per row of (n, k) ``values`` the median under non-negative ``weights`` (n, k): (n,)."""
    order = values.argsort(axis=1)
    v = np.take_along_axis(values, order, axis=1)
    w = np.take_along_axis(weights, order, axis=1).cumsum(axis=1)
    half = (w < 0.5 * w[:, -1:]).sum(axis=1)  # first column where the cumulative weight reaches half
    return v[np.arange(len(v)), half]


def _basis(t: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Columns 1, e^-g1t cos w1t, e^-g1t sin w1t, e^-g2t cos w2t, e^-g2t sin w2t for members theta (S, 4) of
    (f1 (Hz), g1 (1/s), f2 / f1, g2 / g1): (S, n, 5)."""
    f1, g1, rf, rg = (theta[:, i, None] for i in range(4))  # (S, 1) each
    cols = [np.ones((len(theta), len(t)))]
    for f, g in ((f1, g1), (f1 * rf, g1 * rg)):
        envelope = np.exp(-g * t)  # (S, n)
        cols += [envelope * np.cos(2 * np.pi * f * t), envelope * np.sin(2 * np.pi * f * t)]
    return np.stack(cols, axis=2)


def _solve_linear(basis: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares of each member's targets y (S, n) on its basis (S, n, 5), ridge on the four amplitudes
    (not the offset, which a still surface must get whole): coefficients (S, 5)."""
    gram = np.einsum("snp,snq->spq", basis, basis)
    gram += RIDGE * basis.shape[1] * np.diag([0.0, 1.0, 1.0, 1.0, 1.0])
    return np.linalg.solve(gram, np.einsum("snp,sn->sp", basis, y)[..., None])[..., 0]


def _follow(basis: np.ndarray, y: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each member's curve (S, n) and per-frame gap to its nearest candidate (S, n): fit the targets y (S, n),
    then ALTERNATIONS times take per frame the candidate nearest the curve and refit through those."""
    for _ in range(ALTERNATIONS + 1):
        curve = np.einsum("snp,sp->sn", basis, _solve_linear(basis, y))
        gap = candidates[None] - curve[:, :, None]  # (S, n, k)
        nearest = np.abs(gap).argmin(axis=2)[..., None]  # (S, n, 1)
        y = curve + np.take_along_axis(gap, nearest, axis=2)[..., 0]
    return curve, y - curve


def _huber(residual: np.ndarray, scale: float) -> np.ndarray:
    a = np.abs(residual)
    return np.where(a <= scale, 0.5 * a * a, scale * (a - 0.5 * scale))


def _modes(theta: np.ndarray, linear: np.ndarray, duration: float) -> tuple[np.ndarray, float]:
    """(f1, g1, f2/f1, g2/g1) and (zeta, c1, s1, c2, s2) -> modes (2, 4) as in :class:`RegularisedFit`, zeta.

    The dominant mode comes first: the one whose envelope A exp(-g t) covers more of the window (mode 1
    by construction, unless its amplitude vanished and mode 2 carries the oscillation)."""
    f1, g1, rf, rg = theta
    zeta, c1, s1, c2, s2 = linear
    # c cos(wt) + s sin(wt) = A cos(wt + phi) with A = hypot(c, s), phi = atan2(-s, c)
    modes = np.array([[f1, g1, np.hypot(c1, s1), np.arctan2(-s1, c1) % (2 * np.pi)],
                      [f1 * rf, g1 * rg, np.hypot(c2, s2), np.arctan2(-s2, c2) % (2 * np.pi)]])
    g = np.maximum(modes[:, 1], 1e-12)
    envelope = modes[:, 2] * -np.expm1(-g * duration) / g  # (2,): integral of A exp(-g t) over the window
    return modes[np.argsort(-envelope, kind="stable")], float(zeta)


def fit_window(candidates: np.ndarray, fps: float, distances: np.ndarray | None = None, seed: int = 0) -> RegularisedFit:
    """Fit one window: ``candidates`` (n, k) of D(0) in mm for n consecutive frames at ``fps``, with their
    image ``distances`` (n, k) (nearest first; without them every candidate weighs the same)."""
    c = np.asarray(candidates, np.float64)
    if c.ndim != 2 or c.shape[0] < 4 or c.shape[1] < 1:
        raise MeniscopeError("candidates", f"need (frames >= 4, k >= 1), got shape {c.shape}")
    if not np.all(np.isfinite(c)) or not (np.isfinite(fps) and fps > 0):
        raise MeniscopeError("candidates", "candidates and fps must be finite (fps > 0)")
    e = np.ones_like(c) if distances is None else np.asarray(distances, np.float64)
    if e.shape != c.shape or not np.all(np.isfinite(e)) or np.any(e < 0):
        raise MeniscopeError("distances", f"need finite non-negative distances of shape {c.shape}, got {e.shape}")
    n = c.shape[0]
    t = np.arange(n) / fps
    duration = n / fps
    weights = (np.maximum(e[:, :1], 1e-12) / np.maximum(e, 1e-12)) ** 2  # (n, k), 1 for the nearest
    picks = weighted_median(c, weights)  # (n,)
    lo, hi = np.percentile(picks, [5, 95])
    scale = max(ROBUST_FRACTION * (hi - lo), 1e-6)  # mm: a still surface still has a scale
    ratio = L2 / L1
    bounds = [(0.5 / duration, MAX_CYCLES_PER_FRAME * fps / (ratio * (1 + RATIO_TOLERANCE))),  # f1, Hz
              (0.0, MAX_EFOLDS / duration),  # g1, 1/s
              (ratio * (1 - RATIO_TOLERANCE), ratio * (1 + RATIO_TOLERANCE)),  # f2 / f1
              (1.0, MAX_DECAY_RATIO)]  # g2 / g1

    def objective(theta: np.ndarray) -> np.ndarray:
        basis = _basis(t, theta.T)  # theta (4, S)
        residual = picks - np.einsum("snp,sp->sn", basis, _solve_linear(basis, np.broadcast_to(picks, basis.shape[:2])))
        return _huber(residual, scale).sum(axis=1)  # (S,)

    result = differential_evolution(objective, bounds, popsize=POPSIZE, maxiter=MAXITER, tol=TOL, seed=seed,
                                    vectorized=True, updating="deferred", polish=False, init="sobol")
    theta = result.x
    shifts = np.linspace(c.min() - picks.max(), c.max() - picks.min(), SHIFTS)  # (SHIFTS,)
    basis = np.broadcast_to(_basis(t, theta[None]), (SHIFTS, n, 5))
    curve, gap = _follow(basis, picks + shifts[:, None], c)
    best = _huber(gap, scale).sum(axis=1).argmin()
    centre = curve[best] + gap[best]
    linear = _solve_linear(basis[:1], centre[None])[0]

    def residuals(x: np.ndarray) -> np.ndarray:  # the frames' misfit, then the ridge on the four amplitudes
        misfit = np.einsum("np,p->n", _basis(t, x[None, :4])[0], x[4:]) - centre
        return np.concatenate([misfit, np.sqrt(RIDGE * n) * x[5:]])

    lower = [b[0] for b in bounds] + [-np.inf] * 5
    upper = [b[1] for b in bounds] + [np.inf] * 5
    start = np.clip(np.concatenate([theta, linear]), lower, upper)
    final = least_squares(residuals, start, bounds=(lower, upper), loss="soft_l1", f_scale=scale, x_scale="jac",
                          max_nfev=50)
    modes, zeta = _modes(final.x[:4], final.x[4:], duration)
    chosen = np.abs(c - centre[:, None]).argmin(axis=1)
    rms = float(np.sqrt(np.mean(final.fun[:n] ** 2)))
    return RegularisedFit(modes=modes, offset_mm=zeta, centre=centre, chosen=chosen, rms_mm=rms)
