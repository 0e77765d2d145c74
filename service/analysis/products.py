"""A window's poles from its frames' brightness through the brightness' nonlinearity (issue 17).

The mean brightness of a frame is a smooth but nonlinear function of the surface's shape: a highlight moves,
grows and clips as the meniscus swings. Within a window it is a function of the two modes alone,
B(n) = F(x1(n), x2(n)) with x_k = exp(-g_k n) cos(w_k n + phi_k), so besides each mode it holds their harmonics
and their sum and difference frequencies, and (from F's cubic terms) a part at each mode's frequency that decays
at three times its rate. A fit of damped modes alone takes these for modes or folds them into the modes it has,
and their decay rates with them (docs/benchmarks.md). Here F is its Taylor polynomial of degree :data:`ORDER`,
whose coefficients are linear, and the six parameters (w, g, phi of each mode) are found by variable projection
(Golub & Pereyra 1973, Kaufman's Jacobian) with Levenberg-Marquardt, in sample units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.special import stdtrit

#: Degree of F's Taylor polynomial in (x1, x2): the highest of 2, 3 and 4 was the closest on Blender Cycles (docs).
ORDER = 4
#: The monomials x1^i x2^j, 0 < i + j <= ORDER, as the exponent arrays (M,) of x1 and of x2.
_I, _J = np.array([(i, j) for i in range(ORDER + 1) for j in range(ORDER + 1 - i) if i + j > 0]).T
#: Levenberg-Marquardt: iterations at most, and the relative fall in cost under which it has converged.
_ITERATIONS, _TOLERANCE = 60, 1e-8
#: Mode 2's start against mode 1's: Eq. 1's second mode lies at l2 / l1 = 2.30 times the first's frequency and
#: damps faster (a start only: the fit finds both).
_RATIO_W, _RATIO_G = 2.3, 2.0


@dataclass(frozen=True)
class ProductFit:
    """The two modes' poles (w, g per sample) and the half-widths of w and g at the confidence asked, (2,) each,
    mode 1 (the start's) first."""

    w: np.ndarray
    g: np.ndarray
    w_half: np.ndarray
    g_half: np.ndarray


@njit(cache=True, nogil=True, error_model="numpy")
def _projected(
    n: np.ndarray, y: np.ndarray, theta: np.ndarray, first: np.ndarray, second: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Residual (N,) of the linear fit (the offset and each monomial x1^first x2^second) at ``theta`` (w1, g1,
    phi1, w2, g2, phi2), Kaufman's Jacobian (N, 6) of it in ``theta``, and the cost."""
    size, monomials = n.size, first.size
    x = np.empty((2, size))
    dx = np.empty((2, 3, size))  # dx_k / d(w_k, g_k, phi_k) = (-n e sin, -n x, -e sin)
    for k in range(2):
        w, g, phi = theta[3 * k], theta[3 * k + 1], theta[3 * k + 2]
        for i in range(size):
            envelope = np.exp(-g * n[i])
            angle = w * n[i] + phi
            x[k, i] = envelope * np.cos(angle)
            dx[k, 0, i] = -n[i] * envelope * np.sin(angle)
            dx[k, 1, i] = -n[i] * x[k, i]
            dx[k, 2, i] = -envelope * np.sin(angle)
    top = max(first.max(), second.max())
    power = np.ones((2, top + 1, size))  # power[k, e] = x_k^e
    for e in range(1, top + 1):
        power[:, e] = power[:, e - 1] * x
    design = np.empty((size, monomials + 1))
    design[:, 0] = 1.0
    for m in range(monomials):
        design[:, m + 1] = power[0, first[m]] * power[1, second[m]]
    q, r = np.linalg.qr(design)
    q, r = np.ascontiguousarray(q), np.ascontiguousarray(r)
    qy = q.T @ y
    c = np.empty(monomials + 1)  # R c = Q^T y, by back-substitution
    for m in range(monomials, -1, -1):
        c[m] = (qy[m] - r[m, m + 1 :] @ c[m + 1 :]) / r[m, m]
    residual = y - q @ qy
    slope = np.zeros((2, size))  # dF / dx_k at each sample
    for m in range(monomials):
        a, b = first[m], second[m]
        if a:
            slope[0] += c[m + 1] * a * power[0, a - 1] * power[1, b]
        if b:
            slope[1] += c[m + 1] * b * power[0, a] * power[1, b - 1]
    change = np.empty((size, 6))
    for p in range(3):
        change[:, p] = dx[0, p] * slope[0]
        change[:, 3 + p] = dx[1, p] * slope[1]
    jacobian = q @ (q.T @ change) - change
    return residual, jacobian, float(residual @ residual)


@njit(cache=True, nogil=True, error_model="numpy")
def _levenberg_marquardt(
    n: np.ndarray, y: np.ndarray, theta: np.ndarray, first: np.ndarray, second: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """The least-squares ``theta`` from the start ``theta`` (:func:`_projected`'s model), the Jacobian and cost
    there, and whether it converged (the cost falling by under :data:`_TOLERANCE` of itself, or no step lowering
    it) within :data:`_ITERATIONS`; decay rates are held at 0 or above (a growing mode is no mode, and its powers
    overflow)."""
    residual, jacobian, cost = _projected(n, y, theta, first, second)
    damping = 1e-3
    for _ in range(_ITERATIONS):
        normal = jacobian.T @ jacobian
        gradient = jacobian.T @ residual
        while True:
            lhs = normal.copy()
            for p in range(6):
                lhs[p, p] += damping * (normal[p, p] + 1e-12)
            trial = theta - np.linalg.solve(lhs, gradient)
            for k in range(2):
                trial[3 * k + 1] = max(trial[3 * k + 1], 0.0)
            trial_residual, trial_jacobian, trial_cost = _projected(n, y, trial, first, second)
            if trial_cost < cost:
                break
            damping *= 4.0
            if damping > 1e8:  # no step lowers the cost: at the minimum
                return theta, jacobian, cost, True
        converged = cost - trial_cost <= _TOLERANCE * cost
        theta, residual, jacobian, cost = trial, trial_residual, trial_jacobian, trial_cost
        damping = max(damping / 3.0, 1e-9)
        if converged:
            return theta, jacobian, cost, True
    return theta, jacobian, cost, False


def _phases(n: np.ndarray, y: np.ndarray, w: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Each mode's phase (2,) at poles ``w``, ``g``: from the linear fit of the offset and the damped cosines and
    sines."""
    envelope = np.exp(-g[:, None] * n)
    design = np.column_stack(
        [np.ones(n.size), *(envelope * np.cos(w[:, None] * n)), *(envelope * np.sin(w[:, None] * n))]
    )
    c = np.linalg.lstsq(design, y, rcond=None)[0]
    return np.arctan2(-c[3:5], c[1:3])


def fit(n: np.ndarray, y: np.ndarray, w1: float, g1: float, confidence: float) -> ProductFit | None:
    """The brightness ``y`` (N,) at samples ``n`` (N,) fitted as F(x1, x2) from mode 1 at (``w1``, ``g1``) per
    sample (mode 2 starting at :data:`_RATIO_W` times its frequency); None where the fit does not converge, leaves
    the frequencies' range (0, pi), gives a negative decay or has no residual degrees of freedom."""
    dof = n.size - (1 + _I.size) - 6
    if dof < 1:
        return None
    w = np.array([w1, min(_RATIO_W * w1, 0.9 * np.pi)])
    g = np.array([g1, _RATIO_G * g1])
    phi = _phases(n, y, w, g)
    try:
        theta, jacobian, cost, converged = _levenberg_marquardt(
            n, y, np.array([w[0], g[0], phi[0], w[1], g[1], phi[1]]), _I, _J
        )
    except np.linalg.LinAlgError:  # a singular step or design: the modes' columns became dependent
        return None
    if not converged:
        return None
    w, g = np.abs(theta[0::3]), theta[1::3]  # cos is even: a negative frequency is the same mode
    if not (np.all(np.isfinite(theta)) and np.all(w < np.pi) and np.all(g >= 0)):
        return None
    normal = jacobian.T @ jacobian
    try:
        variance = np.diag(np.linalg.inv(normal)) * cost / dof
    except np.linalg.LinAlgError:
        return None
    half = float(stdtrit(dof, 0.5 + confidence / 2)) * np.sqrt(np.maximum(variance, 0.0))
    return ProductFit(w, g, half[0::3], half[1::3])
