"""The window fit's inner loops, compiled (numba): model and Jacobian, soft-L1, IRLS, Levenberg-Marquardt.

Why compiled: a window's fit is a few hundred small array operations (190 samples, at most 10
parameters); in numpy each costs 3-5 us of call overhead, which put the fit at 3.4-8 ms per window
against the 2 ms the live service needs. Here they run as loops in machine code. The model is

    c + v n + sum_k exp(-g_k n) (a_k cos w_k n + b_k sin w_k n),   n in samples since the window start,

with parameters (c, v, a_1, b_1, w_1, g_1, ...). ``robust`` selects the soft-L1 loss of scale
``scale``: residuals are rescaled so that their sum of squares is the soft-L1 cost.

Compiled code is cached next to this file (``cache=True``); ``deploy/install.sh`` and the container
build call :func:`service.analysis.fit.warm` so that the service's first window does not wait for the compiler.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from service.analysis.segment import MAD_TO_SIGMA

BASE = 2  # offset c, drift v
PER_MODE = 4  # a, b, w (rad/sample), g (1/sample)

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def _steps(params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each mode's step from one sample to the next, exp(-g) cos w and exp(-g) sin w, (M,) each."""
    modes = (params.size - BASE) // PER_MODE
    step_c, step_s = np.empty(modes), np.empty(modes)
    for m in range(modes):
        w, g = params[BASE + PER_MODE * m + 2], params[BASE + PER_MODE * m + 3]
        step = np.exp(-g)
        step_c[m], step_s[m] = step * np.cos(w), step * np.sin(w)
    return step_c, step_s


@njit(inline="always", **_JIT)
def _advance(
    t: float,
    stepped: bool,
    params: np.ndarray,
    step_c: np.ndarray,
    step_s: np.ndarray,
    cosine: np.ndarray,
    sine: np.ndarray,
    out_c: np.ndarray,
    out_s: np.ndarray,
) -> None:
    """The modes' damped cosines and sines at sample ``t`` (M,) into ``out_c``, ``out_s``: one step from those at
    the sample before (``cosine``, ``sine``) where ``stepped``, else computed directly (``out`` may be ``cosine``)."""
    for m in range(step_c.size):
        if stepped:
            c, s = cosine[m], sine[m]
            out_c[m], out_s[m] = c * step_c[m] - s * step_s[m], c * step_s[m] + s * step_c[m]
        else:
            w, g = params[BASE + PER_MODE * m + 2], params[BASE + PER_MODE * m + 3]
            e = np.exp(-g * t)
            out_c[m], out_s[m] = e * np.cos(w * t), e * np.sin(w * t)


@njit(**_JIT)
def oscillations(n: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """exp(-g t) cos(w t) and exp(-g t) sin(w t) of each mode at each sample, (N, M) each.

    Consecutive samples step by one complex product, z(t + 1) = z(t) exp(-g + i w), instead of an exp, a cos and a sin
    per sample (three quarters of an evaluation's time); the first sample and each one after a gap are computed
    directly. The rounding this accumulates is ~N ulp (2e-13 at 2,000 samples), far under any interval."""
    step_c, step_s = _steps(params)
    cosines, sines = np.empty((n.size, step_c.size)), np.empty((n.size, step_c.size))
    for i in range(n.size):
        before = max(i - 1, 0)
        stepped = i > 0 and n[i] - n[i - 1] == 1.0
        _advance(n[i], stepped, params, step_c, step_s, cosines[before], sines[before], cosines[i], sines[i])
    return cosines, sines


@njit(inline="always", **_JIT)
def _sample(t: float, params: np.ndarray, cosines: np.ndarray, sines: np.ndarray, row: np.ndarray) -> float:
    """The model at ``t`` (returned) and its gradient in ``params`` (into ``row``, (k,)) from the modes' damped cosines
    and sines there (M,): 1, t, then per mode e cos, e sin, d/dw = -t e (a sin - b cos), d/dg = -t e (a cos + b sin),
    with e = exp(-g t)."""
    value = params[0] + params[1] * t
    row[0], row[1] = 1.0, t
    for m in range(cosines.size):
        j = BASE + PER_MODE * m
        a, b = params[j], params[j + 1]
        ec, es = cosines[m], sines[m]
        mode = a * ec + b * es
        value += mode
        row[j], row[j + 1] = ec, es
        row[j + 2] = -t * (a * es - b * ec)
        row[j + 3] = -t * mode
    return value


@njit(inline="always", **_JIT)
def _soft_l1(r: float, scale: float) -> tuple[float, float]:
    """One residual as minimised under the soft-L1 loss and its derivative in the plain residual (:func:`rescaled`)."""
    z = (r / scale) ** 2
    root = np.sqrt(1.0 + z)
    weight = np.sqrt(2.0 / (root + 1.0))
    return r * weight, weight * (1.0 - z / (2.0 * root * (root + 1.0)))


@njit(**_JIT)
def columns(n: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Model (N,) and Jacobian (N, 2 + 4 M) at ``params`` (columns as :func:`_sample` writes them)."""
    cosines, sines = oscillations(n, params)
    model = np.empty(n.size)
    jac = np.empty((n.size, params.size))
    for i in range(n.size):
        model[i] = _sample(n[i], params, cosines[i], sines[i], jac[i])
    return model, jac


@njit(**_JIT)
def rescaled(r: np.ndarray, scale: float, robust: bool) -> tuple[np.ndarray, np.ndarray]:
    """Residuals as minimised and their derivative in the plain residual.

    Soft-L1: ``sum r'^2 = sum C^2 rho(r^2 / C^2)``, ``rho(z) = 2 (sqrt(1 + z) - 1)`` (quadratic below
    the scale C, linear above), written ``r' = r sqrt(2 / (sqrt(1 + z) + 1))`` so that it is smooth at 0."""
    if not robust:
        return r.copy(), np.ones_like(r)
    out, slope = np.empty_like(r), np.empty_like(r)
    for i in range(r.size):
        out[i], slope[i] = _soft_l1(r[i], scale)
    return out, slope


@njit(**_JIT)
def _weighted(
    n: np.ndarray, y: np.ndarray, scale: float, robust: bool, params: np.ndarray, chain: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals as minimised (N,) and their Jacobian (N, k), each column times ``chain`` (k,), in one pass over
    the samples: the search's inner loop (one evaluation of LM), so nothing is allocated per sample; the modes'
    damped cosines and sines stepped as :func:`oscillations` steps them (the same bits), sample by sample."""
    step_c, step_s = _steps(params)
    cosine, sine = np.empty(step_c.size), np.empty(step_c.size)
    r = np.empty(n.size)
    jac = np.empty((n.size, params.size))
    for i in range(n.size):
        t = n[i]
        _advance(t, i > 0 and t - n[i - 1] == 1.0, params, step_c, step_s, cosine, sine, cosine, sine)
        row = jac[i]
        residual = _sample(t, params, cosine, sine, row) - y[i]
        slope = 1.0
        if robust:
            residual, slope = _soft_l1(residual, scale)
        r[i] = residual
        for j in range(params.size):
            row[j] *= slope * chain[j]
    return r, jac


@njit(**_JIT)
def weighted_jacobian(
    n: np.ndarray, y: np.ndarray, scale: float, robust: bool, params: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals as minimised (N,) and their Jacobian in the model parameters (N, k)."""
    return _weighted(n, y, scale, robust, params, np.ones(params.size))


@njit(**_JIT)
def _search_point(
    n: np.ndarray, y: np.ndarray, scale: float, robust: bool, x: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals and Jacobian at a search point x, where each decay g is x^2 (so g >= 0 without bounds)."""
    params = x.copy()
    chain = np.ones(x.size)
    for j in range(BASE + 3, x.size, PER_MODE):
        params[j] = x[j] * x[j]
        chain[j] = 2.0 * x[j]
    return _weighted(n, y, scale, robust, params, chain)


@njit(**_JIT)
def _fastest_decay(x: np.ndarray) -> float:
    """The largest decay g = x^2 of a search point's modes (0 without modes)."""
    fastest = 0.0
    for j in range(BASE + 3, x.size, PER_MODE):
        fastest = max(fastest, x[j] * x[j])
    return fastest


@njit(**_JIT)
def damped_solve(normal: np.ndarray, damping: np.ndarray, rhs: np.ndarray, out: np.ndarray) -> bool:
    """``(normal + diag(damping))^-1 rhs`` (k,) into ``out`` by Cholesky, and whether the matrix (symmetric, only
    its lower triangle read) was positive definite to machine precision and the solution finite: the step of
    :mod:`service.analysis.products`' LM, where LAPACK's LU through ``np.linalg.solve`` cost three times as much
    at k <= 10 (docs/benchmarks.md; the window fit's LM keeps LU: its last digits tipped a short window)."""
    k = rhs.size
    lower = np.empty((k, k))
    for j in range(k):
        pivot = normal[j, j] + damping[j]
        for p in range(j):
            pivot -= lower[j, p] * lower[j, p]
        if not pivot > 0.0 or not np.isfinite(pivot):
            return False
        lower[j, j] = np.sqrt(pivot)
        for i in range(j + 1, k):
            total = normal[i, j]
            for p in range(j):
                total -= lower[i, p] * lower[j, p]
            lower[i, j] = total / lower[j, j]
    for i in range(k):  # L z = rhs
        total = rhs[i]
        for p in range(i):
            total -= lower[i, p] * out[p]
        out[i] = total / lower[i, i]
    for i in range(k - 1, -1, -1):  # L' x = z
        total = out[i]
        for p in range(i + 1, k):
            total -= lower[p, i] * out[p]
        out[i] = total / lower[i, i]
        if not np.isfinite(out[i]):  # a pivot positive but tiny (subnormal): the solution overflows
            return False
    return True


@njit(**_JIT)
def levenberg_marquardt(
    n: np.ndarray,
    y: np.ndarray,
    scale: float,
    robust: bool,
    params: np.ndarray,
    tolerance: float,
    evaluations: int,
    free: np.ndarray | None = None,
    max_decay: float = np.inf,
) -> np.ndarray:
    """Least-squares optimum of the model near ``params``, by Levenberg-Marquardt with Marquardt's scaling.

    Each trial solves (J'J + mu D) h = -J'r, D the largest diag(J'J) seen so far (as MINPACK scales),
    and mu follows Nielsen's gain-ratio rule. It stops when a step changes the cost or the scaled point
    by under ``tolerance`` (relative), or after ``evaluations`` evaluations: a search that has not
    converged by then has a mode its data do not pin down, and is judged from where it stopped. Parameters
    where ``free`` (k,) is False keep their start values (the drift of a window fitted without one); all are
    free without it. It also stops once a step takes a mode's decay over ``max_decay`` (1/sample): such a mode is
    chasing the window's first samples (its amplitude grows as its decay does, over hundreds of evaluations that
    barely lower the cost), and whatever follows, it is judged a transient, not a resolved oscillation."""
    x = params.copy()
    for j in range(BASE + 3, x.size, PER_MODE):
        x[j] = np.sqrt(max(x[j], 0.0))
    r, jac = _search_point(n, y, scale, robust, x)
    cost = r @ r
    k = x.size
    fixed = np.zeros(k, np.bool_) if free is None else ~free
    diag = np.zeros(k)
    mu, nu = 1e-3, 2.0
    moved = True  # x moved since the normal matrix was formed (a rejected trial leaves it, and it, as they were)
    normal, gradient = np.empty((k, k)), np.empty(k)
    for _ in range(evaluations - 1):
        if moved:
            normal = jac.T @ jac
            gradient = jac.T @ r
            for j in range(k):
                if fixed[j]:  # a step of exactly 0 in it
                    normal[j, :] = 0.0
                    normal[:, j] = 0.0
                    normal[j, j] = 1.0
                    gradient[j] = 0.0
                diag[j] = max(diag[j], normal[j, j], 1e-300)
            if not np.all(np.isfinite(normal)) or np.max(np.abs(gradient)) <= 1e-15 * max(cost, 1e-300):
                break
            moved = False
        system = normal.copy()
        for j in range(k):
            system[j, j] += mu * diag[j]
        try:
            step = np.linalg.solve(system, -gradient)
        except Exception:  # singular to machine precision (a parameter the data do not move): damp harder
            if mu > 1e30:
                break
            mu *= nu
            nu *= 2.0
            continue
        trial = x + step
        r_new, jac_new = _search_point(n, y, scale, robust, trial)
        cost_new = r_new @ r_new
        predicted = step @ (mu * diag * step - gradient)  # cost decrease the linear model promises (> 0)
        ratio = (cost - cost_new) / predicted if predicted > 0 else -1.0
        small_step = np.sqrt(np.sum(diag * step**2)) <= tolerance * np.sqrt(np.sum(diag * x**2))
        if ratio > 0 and np.isfinite(cost_new):
            small_change = cost - cost_new <= tolerance * cost and predicted <= tolerance * cost
            x, r, jac, cost = trial, r_new, jac_new, cost_new
            moved = True
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3)
            nu = 2.0
            if small_change or small_step or _fastest_decay(x) > max_decay:
                break
        else:
            if small_step or mu > 1e30:
                break
            mu *= nu
            nu *= 2.0
    for j in range(BASE + 3, x.size, PER_MODE):
        x[j] = x[j] * x[j]
    return x


@njit(**_JIT)
def canonical(params: np.ndarray) -> np.ndarray:
    """``params`` with each mode's w folded into [0, pi] (cos even, sin odd: b changes sign); g as it is (>= 0 from the search)."""
    p = params.copy()
    for j in range(BASE, p.size, PER_MODE):
        w = np.mod(p[j + 2] + np.pi, 2 * np.pi) - np.pi
        if w < 0:
            p[j + 1] *= -1.0
        p[j + 2] = np.abs(w)
    return p


@njit(**_JIT)
def linear_start(n: np.ndarray, y: np.ndarray, w: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Parameters with modes at frequencies ``w`` and decays ``g`` (M,), the offset, drift and each mode's
    (a, b) by linear least squares: the start of the search for M modes."""
    modes = w.size
    params = np.zeros(BASE + PER_MODE * modes)
    for m in range(modes):
        params[BASE + PER_MODE * m + 2] = w[m]
        params[BASE + PER_MODE * m + 3] = g[m]
    _, design = columns(n, params)
    linear = np.empty(BASE + 2 * modes, np.int64)
    linear[0], linear[1] = 0, 1
    for m in range(modes):
        linear[BASE + 2 * m] = BASE + PER_MODE * m
        linear[BASE + 2 * m + 1] = BASE + PER_MODE * m + 1
    coefficients = np.linalg.lstsq(np.ascontiguousarray(design[:, linear]), y)[0]
    params[linear] = coefficients
    return params


@njit(inline="always", **_JIT)
def _clip(value: float, low: float, high: float) -> float:
    """``np.clip`` of one value (NaN stays NaN)."""
    if value < low:
        return low
    if value > high:
        return high
    return value


@njit(**_JIT)
def mode_start(n: np.ndarray, y: np.ndarray, w: np.ndarray, g: np.ndarray, order: int, max_decay: float) -> np.ndarray:
    """:func:`linear_start` of ``order`` modes at the first of the poles ``w``, ``g`` (most energetic first), half a
    cycle and an e-fold per window for those it lacks; w within [1e-3, pi - 1e-3], g within [1e-4, ``max_decay``]."""
    span = max(n[-1], 1.0)
    ws, gs = np.empty(order), np.empty(order)
    for m in range(order):
        ws[m] = _clip(w[m] if m < w.size else np.pi / span, 1e-3, np.pi - 1e-3)
        gs[m] = _clip(g[m] if m < g.size else 1.0 / span, 1e-4, max_decay)
    return linear_start(n, y, ws, gs)


@njit(**_JIT)
def linear_fit(design: np.ndarray, y: np.ndarray, scale: float, robust: bool, steps: int) -> tuple[np.ndarray, float]:
    """Coefficients of ``design`` (N, k) and their robust cost, by iteratively reweighted least squares.

    For a linear model this reaches the optimum LM would; the soft-L1 weight is
    rho'(z) = 1 / sqrt(1 + z), z = (r / C)^2. Stops when the cost changes by under 1e-6 (relative):
    the BIC differences that matter are far larger."""
    weight = np.ones_like(y)
    cost = np.inf
    coefficients = np.zeros(design.shape[1])
    for _ in range(steps):
        weighted = design.T * weight
        coefficients = np.linalg.solve(weighted @ design, weighted @ y)
        residual = design @ coefficients - y
        minimised, _ = rescaled(residual, scale, robust)
        previous, cost = cost, minimised @ minimised
        if not robust or previous - cost <= 1e-6 * cost:
            break
        weight = 1.0 / np.sqrt(1.0 + (residual / scale) ** 2)
    return coefficients, cost


@njit(**_JIT)
def triangle(jac: np.ndarray) -> np.ndarray:
    """R (k, k) of J = Q R (N, k), N >= k, by Householder reflections without forming Q: R has J's singular values
    and right singular vectors (LAPACK's QR through numba also builds Q, 3-80x the cost at 190-2,000 samples)."""
    size, k = jac.shape
    columns = np.ascontiguousarray(jac.T)  # (k, N): each column of J contiguous
    for j in range(k):
        pivot = columns[j, j:]
        norm = np.sqrt(pivot @ pivot)
        if norm == 0.0:
            continue
        alpha = -norm if pivot[0] > 0 else norm  # the reflection's image of the column: no cancellation in v[0]
        v = pivot.copy()
        v[0] -= alpha
        vv = v @ v
        for c in range(j, k):
            rest = columns[c, j:]
            rest -= (2.0 * (v @ rest) / vv) * v
    out = np.zeros((k, k))
    for i in range(k):
        out[i, i:] = columns[i:, i]
    return out


@njit(**_JIT)
def covariance_diagonal(jac: np.ndarray) -> np.ndarray:
    """diag((J'J)^-1), shape (k,), inf for every parameter when a direction is (numerically) unidentifiable."""
    k = jac.shape[1]
    norms = np.sqrt(np.sum(jac**2, axis=0))
    if not np.all(norms > 0) or not np.all(np.isfinite(jac)):
        return np.full(k, np.inf)
    _, sv, vt = np.linalg.svd(triangle(jac / norms))  # R's SVD is J's, at a tenth of its cost
    if sv[-1] <= 1e-10 * sv[0]:
        return np.full(k, np.inf)
    return np.sum((vt.T / sv) ** 2, axis=1) / norms**2


@njit(**_JIT)
def judged(
    n: np.ndarray, y: np.ndarray, scale: float, robust: bool, params: np.ndarray, drift: bool, t: float
) -> tuple[float, np.ndarray]:
    """A fit's cost (its residuals' sum of squares as minimised) and its parameters' confidence half-widths, ``t``
    standard errors (residual variance over N - k); 0 for the drift where it was held at 0 (``drift`` False), inf
    where a direction is unidentifiable. One call for what took the fit's judge six numpy round trips."""
    r, jac = weighted_jacobian(n, y, scale, robust, params)
    cost = r @ r
    k = params.size
    if not drift:  # the drift's column left out: it is neither counted nor given an interval
        k -= 1
        kept = np.empty((n.size, k))
        kept[:, :1] = jac[:, :1]
        kept[:, 1:] = jac[:, 2:]
        jac = kept
    variance = covariance_diagonal(jac) * cost / (n.size - k)
    half = np.zeros(params.size)
    offset = 0
    for j in range(params.size):
        if j == 1 and not drift:
            offset = 1
            continue
        half[j] = t * np.sqrt(variance[j - offset])
    return cost, half


@njit(**_JIT)
def step_z(n: np.ndarray, y: np.ndarray, scale: float, robust: bool, params: np.ndarray, index: int) -> float:
    """The Gauss-Newton step of parameter ``index`` from ``params``, in standard errors (residual variance over
    N - k): how far the optimum would move it, were it free; inf where the normal matrix is singular."""
    r, jac = weighted_jacobian(n, y, scale, robust, params)
    normal = jac.T @ jac
    if not np.all(np.isfinite(normal)) or np.linalg.cond(normal) > 1e14:
        return np.inf
    inverse = np.linalg.inv(normal)
    step = -(inverse @ (jac.T @ r))[index]
    variance = inverse[index, index] * (r @ r) / max(n.size - params.size, 1)
    return abs(step) / np.sqrt(variance) if variance > 0 else np.inf


@njit(**_JIT)
def median(values: np.ndarray) -> float:
    """``np.median`` of ``values`` (N,, N >= 1) to the last bit (the mean of the middle two where N is even; NaN
    with a NaN), compiled: numpy's call overhead is most of its cost here, and a window's fit takes four to six."""
    for v in values:
        if np.isnan(v):  # numba's median, unlike numpy's, does not always propagate it
            return np.nan
    return np.median(values)


@njit(**_JIT)
def difference_noise(n: np.ndarray, y: np.ndarray) -> float:
    """Noise level from first differences of consecutive samples ``n`` (an over-estimate when the signal is fast):
    their :func:`robust_sigma` over sqrt 2, from all differences where fewer than 3 are of consecutive samples."""
    consecutive = np.diff(n) == 1
    diffs = np.diff(y)[consecutive] if consecutive.sum() >= 3 else np.diff(y)
    return robust_sigma(diffs) / np.sqrt(2.0)


@njit(**_JIT)
def robust_sigma(values: np.ndarray) -> float:
    """:func:`service.analysis.segment.robust_sigma` (1.4826 MAD, 0 for no values) to the last bit, compiled."""
    if values.size == 0:
        return 0.0
    return MAD_TO_SIGMA * median(np.abs(values - median(values)))
