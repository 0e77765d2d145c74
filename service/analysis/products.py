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

from service.analysis.kernels import BASE, PER_MODE, damped_solve, oscillations
from service.analysis.student import t_quantile

#: Degree of F's Taylor polynomial in (x1, x2): the highest of 2, 3 and 4 was the closest on Blender Cycles (docs).
ORDER = 4
#: The monomials x1^i x2^j, 0 < i + j <= ORDER, as the exponent arrays (M,) of x1 and of x2.
_I, _J = np.array([(i, j) for i in range(ORDER + 1) for j in range(ORDER + 1 - i) if i + j > 0]).T
#: Levenberg-Marquardt: iterations at most, and the relative fall in cost under which it has converged (1e-6:
#: fewer evaluations than 1e-8 at no cost in accuracy, docs/benchmarks.md).
_ITERATIONS, _TOLERANCE = 60, 1e-6
#: Smallest pivot of the scaled Gram matrix's Cholesky factor, squared, for which the linear fit takes the
#: seminormal equations (its condition number then under ~1e12: refined once, as accurate as a QR); below, the SVD.
_PIVOT = 1e-12
#: Mode 2's start against mode 1's: Eq. 1's second mode lies at l2 / l1 = 2.30 times the first's frequency and
#: damps faster (a start only: the fit finds both).
_RATIO_W, _RATIO_G = 2.3, 2.0


@dataclass(frozen=True)
class ProductFit:
    """The two modes' poles (w, g per sample) and the half-widths of w and g at the confidence asked, (2,) each,
    mode 1 (the start's) first, and the fit's residual sum of squares (fits of one series from other starts compare
    by it)."""

    w: np.ndarray
    g: np.ndarray
    w_half: np.ndarray
    g_half: np.ndarray
    cost: float


@njit(cache=True, nogil=True, error_model="numpy")
def _factor(design: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """A lower-triangular ``L`` (k, k) and column scales ``s`` (k,) with ``S G S = L L'``, G ``design``'s (N, k)
    Gram matrix with its columns scaled to unit norm (Cholesky's), and whether each pivot is over :data:`_PIVOT`
    (else the design is near singular and is not to be squared)."""
    gram = design.T @ design
    width = gram.shape[0]
    scale = np.empty(width)
    lower = np.zeros((width, width))
    ok = True
    for a in range(width):
        ok = ok and gram[a, a] > 0.0
        scale[a] = 1.0 / np.sqrt(gram[a, a]) if gram[a, a] > 0.0 else 1.0
    for a in range(width):
        for b in range(a + 1):
            if not ok:
                break
            total = gram[a, b] * scale[a] * scale[b]
            for k in range(b):
                total -= lower[a, k] * lower[b, k]
            if a > b:
                lower[a, b] = total / lower[b, b]
            elif total > _PIVOT:
                lower[a, a] = np.sqrt(total)
            else:
                ok = False
    return lower, scale, ok


@njit(cache=True, nogil=True, error_model="numpy")
def _solved(lower: np.ndarray, scale: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``G^-1 rhs`` (k, m) for :func:`_factor`'s ``L`` and ``s``: two triangular solves."""
    width, count = rhs.shape
    out = np.empty((width, count))
    for j in range(count):
        for a in range(width):  # L z = S rhs
            total = scale[a] * rhs[a, j]
            for k in range(a):
                total -= lower[a, k] * out[k, j]
            out[a, j] = total / lower[a, a]
        for a in range(width - 1, -1, -1):  # L' u = z; G^-1 rhs = S u
            total = out[a, j]
            for k in range(a + 1, width):
                total -= lower[k, a] * out[k, j]
            out[a, j] = total / lower[a, a]
        for a in range(width):
            out[a, j] *= scale[a]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _least_squares(design: np.ndarray, lower: np.ndarray, scale: np.ndarray, ok: bool, rhs: np.ndarray) -> np.ndarray:
    """The least-squares coefficients (k, m) of ``design`` (N, k) for each column of ``rhs`` (N, m): by the
    seminormal equations with :func:`_factor`'s factor, refined once, where it is ``ok`` (as accurate as a QR solve
    there, without forming a QR each evaluation); else by the SVD of the design with its columns scaled alike,
    the minimum-norm solution where they are dependent."""
    if not ok:
        return np.linalg.lstsq(design * scale, np.ascontiguousarray(rhs), 1e-12)[0] * scale.reshape(-1, 1)
    coefficients = _solved(lower, scale, design.T @ rhs)
    return coefficients + _solved(lower, scale, design.T @ (rhs - design @ coefficients))


@njit(cache=True, nogil=True, error_model="numpy")
def _linear(
    n: np.ndarray, y: np.ndarray, theta: np.ndarray, first: np.ndarray, second: np.ndarray
) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, bool, np.ndarray, np.ndarray, np.ndarray]:
    """Residual (N,) and cost of the linear fit (the offset and each monomial x1^first x2^second) at ``theta``
    (w1, g1, phi1, w2, g2, phi2), and what :func:`_kaufman` needs for its Jacobian: the design (N, M + 1), its
    factor, scales and whether the factor serves, the coefficients (M + 1,), the powers x_k^e (2, E, N) and dx_k / d(w_k, g_k, phi_k)
    (2, 3, N)."""
    size, monomials = n.size, first.size
    poles = np.zeros(BASE + 2 * PER_MODE)  # the modes' w and g in the window fit's layout, for its stepped cosines
    for k in range(2):
        poles[BASE + PER_MODE * k + 2], poles[BASE + PER_MODE * k + 3] = theta[3 * k], theta[3 * k + 1]
    cosines, sines = oscillations(n, poles)  # e cos(w n), e sin(w n): a complex product a sample, not exp, cos, sin
    x = np.empty((2, size))
    dx = np.empty((2, 3, size))  # dx_k / d(w_k, g_k, phi_k) = (-n e sin, -n x, -e sin), angle w n + phi
    for k in range(2):
        cos_phi, sin_phi = np.cos(theta[3 * k + 2]), np.sin(theta[3 * k + 2])
        for i in range(size):
            x[k, i] = cosines[i, k] * cos_phi - sines[i, k] * sin_phi
            dx[k, 2, i] = -(sines[i, k] * cos_phi + cosines[i, k] * sin_phi)
            dx[k, 0, i] = n[i] * dx[k, 2, i]
            dx[k, 1, i] = -n[i] * x[k, i]
    top = max(first.max(), second.max())
    power = np.ones((2, top + 1, size))  # power[k, e] = x_k^e
    for e in range(1, top + 1):
        for k in range(2):
            for i in range(size):
                power[k, e, i] = power[k, e - 1, i] * x[k, i]
    design = np.empty((size, monomials + 1))
    for i in range(size):
        design[i, 0] = 1.0
        for m in range(monomials):
            design[i, m + 1] = power[0, first[m], i] * power[1, second[m], i]
    lower, scale, ok = _factor(design)
    c = np.ascontiguousarray(_least_squares(design, lower, scale, ok, y.reshape(-1, 1))[:, 0])
    residual = y - design @ c
    return residual, float(residual @ residual), design, lower, scale, ok, c, power, dx


@njit(cache=True, nogil=True, error_model="numpy")
def _kaufman(
    design: np.ndarray,
    lower: np.ndarray,
    scale: np.ndarray,
    ok: bool,
    c: np.ndarray,
    power: np.ndarray,
    dx: np.ndarray,
    first: np.ndarray,
    second: np.ndarray,
) -> np.ndarray:
    """Kaufman's Jacobian (N, 6) of :func:`_linear`'s residual: -(I - P) dF/dtheta at fixed coefficients, P the
    projection onto the design's columns."""
    size = design.shape[0]
    change = np.empty((size, 6))  # dF / dx_k times dx_k / d theta, at each sample
    for i in range(size):
        slope0, slope1 = 0.0, 0.0
        for m in range(first.size):
            a, b = first[m], second[m]
            if a:
                slope0 += c[m + 1] * a * power[0, a - 1, i] * power[1, b, i]
            if b:
                slope1 += c[m + 1] * b * power[0, a, i] * power[1, b - 1, i]
        for p in range(3):
            change[i, p] = dx[0, p, i] * slope0
            change[i, 3 + p] = dx[1, p, i] * slope1
    return design @ _least_squares(design, lower, scale, ok, change) - change


@njit(cache=True, nogil=True, error_model="numpy")
def _levenberg_marquardt(
    n: np.ndarray, y: np.ndarray, theta: np.ndarray, first: np.ndarray, second: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """The least-squares ``theta`` from the start ``theta`` (:func:`_linear`'s model), the Jacobian and cost
    there, and whether it converged (the cost falling by under :data:`_TOLERANCE` of itself, or no step lowering
    it) within :data:`_ITERATIONS`; decay rates are held at 0 or above (a growing mode is no mode, and its powers
    overflow). A trial's Jacobian is formed only where the trial is taken."""
    residual, cost, design, lower, scale, ok, c, power, dx = _linear(n, y, theta, first, second)
    jacobian = _kaufman(design, lower, scale, ok, c, power, dx, first, second)
    damping = 1e-3
    for _ in range(_ITERATIONS):
        normal = jacobian.T @ jacobian
        gradient = jacobian.T @ residual
        while True:
            step = np.empty(6)
            if not damped_solve(normal, damping * (np.diag(normal) + 1e-12), gradient, step):
                raise np.linalg.LinAlgError("the damped normal matrix is not positive definite")
            trial = theta - step
            for k in range(2):
                trial[3 * k + 1] = max(trial[3 * k + 1], 0.0)
            trial_residual, trial_cost, design, lower, scale, ok, c, power, dx = _linear(n, y, trial, first, second)
            if trial_cost < cost:
                break
            damping *= 4.0
            if damping > 1e8:  # no step lowers the cost: at the minimum
                return theta, jacobian, cost, True
        converged = cost - trial_cost <= _TOLERANCE * cost
        theta, residual, cost = trial, trial_residual, trial_cost
        jacobian = _kaufman(design, lower, scale, ok, c, power, dx, first, second)
        damping = max(damping / 3.0, 1e-9)
        if converged:
            return theta, jacobian, cost, True
    return theta, jacobian, cost, False


@njit(cache=True, nogil=True, error_model="numpy")
def _phases(n: np.ndarray, y: np.ndarray, w: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Each mode's phase (2,) at poles ``w``, ``g``: from the linear fit of the offset and the damped cosines and
    sines."""
    design = np.empty((n.size, 5))
    for i in range(n.size):
        design[i, 0] = 1.0
        for k in range(2):
            envelope = np.exp(-g[k] * n[i])
            design[i, 1 + k] = envelope * np.cos(w[k] * n[i])
            design[i, 3 + k] = envelope * np.sin(w[k] * n[i])
    c = _least_squares(design, *_factor(design), y.reshape(-1, 1))[:, 0]
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
    half = t_quantile(dof, confidence) * np.sqrt(np.maximum(variance, 0.0))
    if not np.all(np.isfinite(half)):  # a Jacobian gone non-finite where a mode's powers underflowed
        return None
    return ProductFit(w, g, half[0::3], half[1::3], float(cost))
