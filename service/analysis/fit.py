"""The damped-oscillation fit of one window: offset, drift and 0, 1 or 2 damped modes (Eq. 1 at r = 0).

    D(0, t) = c + v t + sum_k A_k exp(-g_k t) cos(2 pi f_k t + phi_k),   t from the window start

Eq. 1 makes ``c = d + p R`` constant in a window; the drift ``v`` is there so that a slow bias of
the upstream estimate is not mistaken for a slow mode, and is fitted only where the data show one
(a drift they do not need trades against a slow decay and a fraction of a cycle: it cost the decay
and frequency their precision). Per model order the matrix pencil gives the start (also from the
strongest gap-free stretch where samples are missing), Levenberg-Marquardt (compiled:
:mod:`service.analysis.kernels`) refines it under a soft-L1 loss whose scale is a robust noise
estimate; samples over 6 robust sd off the chosen fit (spikes) are left out and the window is
fitted again; where none is, the chosen fit is refined once more under plain least squares, the
maximum-likelihood fit under Gaussian noise (soft-L1 weighs down every residual over the noise).
The order is chosen by BIC (with AICc's small-sample term, a mode added only on a gain over 2),
on the soft-L1 fits: it is consistent (with ~190 samples it does not add modes that noise alone explains,
where AIC/AICc would more often), and its log(n) penalty is what makes "settled" mean "no
oscillation above the noise". Confidence intervals come from the Gauss-Newton covariance at the
optimum (Student t); a mode whose frequency interval reaches under 0.8 cycles in the window is not
resolved, so that a slow swing is never reported as a frequency. ``meniscope bench fit`` measures
all of this against peers and the Cramer-Rao bound (docs/benchmarks.md).
"""

from __future__ import annotations

import copy
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike
from tqdm import tqdm

from service import blas
from service.analysis import kernels, pencil, products
from service.analysis.kernels import BASE as _BASE
from service.analysis.kernels import PER_MODE as _PER_MODE
from service.analysis.kernels import robust_sigma
from service.analysis.results import FitSettings, WindowResult
from service.analysis.segment import Window
from service.analysis.settling import Settling, damping_ratio, quality_factor, settle, tolerance
from service.analysis.student import t_quantile
from service.physics import damped_mode

_MIN_DOF = 3  # residual degrees of freedom a model order needs to be tried
#: A mode that decays by e within a frame is a transient, not a resolved oscillation (1/sample).
_MAX_DECAY = 1.0
#: A mode turning less than this many cycles over the window is a slow swing, not a measured frequency.
_MIN_CYCLES = 0.8
#: Series beyond this magnitude are refused: squares of their deviations would overflow float64.
_MAX_VALUE = 1e150
#: Residuals below this fraction of the window's peak deviation count as exact (float64 round-off).
_EXACT = 1e-9
#: Residuals below this fraction count as exact in the order choice: what LM's stopping tolerance
#: (:data:`_LM_TOLERANCE`) leaves of a noise-free window (a pure cosine near Nyquist kept 3e-7 to 7e-7 of its
#: amplitude); below it a second mode would only fit the search's own leftovers.
_CONVERGED = 1e-5
#: LM stops when cost or step change by under this (relative): 1e-6 moves a frequency by ~1e-6 of
#: itself, far inside its confidence interval, in ~30 % fewer evaluations than MINPACK's 1.5e-8.
_LM_TOLERANCE = 1e-6
#: Evaluations per parameter LM may spend (MINPACK's default is 100): a window that has not converged by
#: then has a mode its data do not pin down (real series wander to 1,000 evaluations, 0.3 s); the judge
#: reports it from wherever the search stopped.
_LM_EVALUATIONS = 20
#: Pencil parameter (Hankel rows) of the start: the LM refines the start, so the pencil needs only to
#: separate the 2 M + 2 poles, not Hua & Sarkar's N / 3 (whose SVD is ~10x slower at N = 190).
_PENCIL = 20
#: Pencil pole pairs turning fewer cycles over the window stand in for the offset or a trend.
_PENCIL_MIN_CYCLES = 0.25
#: Lag-one correlation of a fit's residual above which it holds a mode still to find (white noise: 0 +- 0.07 at
#: 190 samples).
_STRUCTURED = 0.5
#: A sample this many robust standard deviations off the one-mode fit is an outlier (a spike): 6 sd is ~1 in 5e8
#: Gaussian samples ...
_OUTLIER = 6.0
#: ... when at most this share of the window's samples is (more is the model missing something, not spikes).
_MAX_OUTLIERS = 0.1
#: Beyond that share, an outlier must stand this many times above the next sample (see :func:`_outliers`).
_SPIKE_GAP = 3.0
#: A mode is added only when it lowers the BIC by more than this: "positive" evidence on Kass & Raftery's (1995)
#: scale; below it, noise alone (a spike left out, a lucky run) adds a mode under the noise ~1 window in 20.
_EVIDENCE = 2.0
#: A fit without drift is tried with one where the drift's step from there is over this many standard errors:
#: ~sqrt(ln n) at 190 samples, where BIC starts to prefer keeping it (a z of 2 already, to be safe).
_DRIFT_TEST = 2.0
#: Modes turning fewer cycles than this over the window are fitted both with and without a drift.
_SWING_CYCLES = 1.5
#: The brightness' polynomial fit replaces its modes' poles only within this relative shift of its start's
#: frequency: further off, it has ended on another mode or a product (the nearest, mode 2 less mode 1, lies ~1.3 times
#: mode 1). Its decay rate is not held to its start's: in heavily damped windows the damped modes fitted to the
#: brightness misread the decay by over a factor of two, and the frequency by over 5 %, where the polynomial reads them
#: right (docs/benchmarks.md, "The brightness polynomial's poles not held to their start").
_PRODUCT_SHIFT = 0.15
#: The brightness' polynomial is also started from the strongest line of its spectrum, at this decay per radian,
#: where that line lies further than :data:`_PRODUCT_SHIFT` from the damped modes' pole (the fit from the lower-cost
#: start is kept), and from it alone where the damped fits resolve none (:func:`_line_poles`): a brightness dominated
#: by the ejection's fading light gave its damped fits no pole near the mode its spectrum shows (docs/benchmarks.md,
#: "The brightness polynomial's poles not held to their start").
_LINE_DECAY = 0.05
#: Fewest cycles over the window the spectrum's strongest line is looked for at (below: the drift's and swing's).
_LINE_CYCLES = 4
#: Radians over which a pole must decay by no more than e to be an oscillation of the surface (issue 17's fluids:
#: >= 3.1): to start the brightness' polynomial fit as mode 1, and to be handed to the window's series.
_UNDERDAMPED = 2.0
#: The brightness' lowest mode is taken at half its frequency and decay rate where the series fitted with that costs
#: under this fraction of its cost with the mode as found: between the windows whose brightness held only the second
#: harmonic and every other (docs/benchmarks.md, "The brightness' second harmonic").
_HALVED_GAIN = 0.9
#: The polynomial's mode 2 is the window's where its frequency's interval is within this fraction of it: a mode of the
#: surface comes out several times sharper, a second mode the polynomial spends on a harmonic or the ejection's light
#: several times wider (docs/benchmarks.md, "The brightness polynomial from the one-mode fit").
_SHARP = 0.01
#: Frequency ratios of the brightness' two poles taken for a mode and its second harmonic (Eq. 1's modes: 2.30).
_HARMONIC_RATIO = (1.8, 2.15)
_IRLS_STEPS = 100  # at most; the order-0 cost settles to 1e-6 (relative) in ~5-10 rounds


#: The linear parameters' indices (offset, drift and each mode's a and b) by number of modes.
_LINEAR = [np.r_[0, 1, (_BASE + _PER_MODE * np.arange(m)[:, None] + np.array([0, 1])).ravel()] for m in range(3)]


def min_samples(order: int) -> int:
    """Finite samples needed to fit ``order`` modes with at least 3 residual degrees of freedom."""
    return _BASE + _PER_MODE * order + _MIN_DOF


@dataclass(frozen=True)
class _OrderFit:
    """The least-squares optimum for one model order, in normalised units (per sample, per scale)."""

    order: int
    params: np.ndarray  # (2 + 4 M,): c, v, (a, b, w, g) per mode, w in [0, pi], g >= 0
    half_width: np.ndarray  # (2 + 4 M,) CI half-widths; inf where not identifiable
    cost: float  # sum of squared (robust) residuals
    bic: float
    problem: str | None  # why its modes are not resolved, None when they are
    poles_from: Literal["series", "frames"] = "series"
    drift: bool = True  # whether the drift v was fitted (else it is 0)


class _Window:
    """One window's normalised data and the per-order fits of the module docstring."""

    def __init__(self, n: np.ndarray, y: np.ndarray, settings: FitSettings) -> None:
        self.n, self.y, self.settings = n, y, settings
        self.scale = max(kernels.difference_noise(n, y), _EXACT)  # soft-L1 scale, normalised units
        self.robust = settings.loss == "soft_l1"
        self.span, self.mean_n = n[-1] - n[0] + 1, n.mean()  # samples the window spans; their mean index
        self.log_n = np.log(n.size)  # BIC's penalty per parameter, asked for ~8 times a window

    def starts(self, order: int, pencil_modes: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """Start for ``order`` modes: the most energetic pencil pairs, linear coefficients by least squares."""
        return kernels.mode_start(self.n, self.y, *pencil_modes, order, _MAX_DECAY)

    def extended(self, fewer: _OrderFit, length: int) -> np.ndarray | None:
        """Start for one mode more than ``fewer``: its modes and the strongest pencil pair of what it leaves; None
        where that residual is white (consecutive residuals correlate under ``_STRUCTURED``): nothing left to find.

        Two modes closer than the short pencil resolves (1.05-1.2 times apart over ~10 cycles) merge into one of its
        poles, and the fit of one mode more from there stays unresolved; the fit of fewer modes sits between them
        and its residual shows the missing mode clearly."""
        model, _ = kernels.columns(self.n, fewer.params)
        residual = self.y - model
        consecutive = np.diff(self.n) == 1
        a, b = residual[:-1][consecutive], residual[1:][consecutive]
        if a.size < 3 or abs(a @ b) < _STRUCTURED * np.sqrt((a @ a) * (b @ b)):
            return None
        w, g = _pencil_modes(self.n, residual, length, 4)
        if w.size == 0:
            return None
        modes = fewer.params[_BASE:].reshape(-1, _PER_MODE)
        return self.starts(
            fewer.order + 1, (np.concatenate((modes[:, 2], w[:1])), np.concatenate((modes[:, 3], g[:1])))
        )

    def without(self, samples: np.ndarray) -> _Window:
        """This window with the ``samples`` (mask over its finite ones) left out."""
        return _Window(self.n[~samples], self.y[~samples], self.settings)

    def polish(self, chosen: _OrderFit) -> _OrderFit:
        """``chosen`` refined under plain least squares (its order and drift kept) and judged so: where no sample
        stood out as a spike, the maximum-likelihood fit under Gaussian noise, with least squares' intervals
        (soft-L1 weighs down every residual over the noise: the frequency's variance grows, the decay's more)."""
        gaussian = copy.copy(self)
        gaussian.robust = False
        free = np.ones(chosen.params.size, dtype=np.bool_)
        free[1] = chosen.drift
        params = gaussian._refine(chosen.params, free)
        return gaussian._judge(chosen.order, params, drift=chosen.drift)

    def bic(self, cost: float, k: int) -> float:
        """n ln(cost / n) + k ln n + 2 k (k + 1) / (n - k - 1), with residuals under ``_CONVERGED`` counted as exact.

        The last term is AICc's small-sample correction: negligible at 190 samples (1.2 for two modes), it stops
        a 20-sample window from taking a second mode that its few residual degrees of freedom cannot refute."""
        n = self.n.size
        return float(n * np.log(cost / n + _CONVERGED**2) + k * self.log_n + 2 * k * (k + 1) / max(n - k - 1, 1))

    def linear_fit(self, design: np.ndarray) -> tuple[np.ndarray, float]:
        """Coefficients of ``design`` (N, k) and their robust cost (:func:`kernels.linear_fit`)."""
        params, cost = kernels.linear_fit(design, self.y, self.scale, self.robust, _IRLS_STEPS)
        return params, float(cost)

    def fit_baseline(self) -> _OrderFit:
        """Order 0: the offset alone, or offset and drift where the criterion prefers them."""
        offset, _ = self.linear_fit(np.ones((self.n.size, 1)))
        line, _ = self.linear_fit(np.stack([np.ones_like(self.n), self.n], axis=1))
        return min(self._judge(0, np.append(offset, 0.0), drift=False), self._judge(0, line), key=lambda f: f.bic)

    def fit(self, order: int, start: np.ndarray, drift_first: bool) -> _OrderFit:
        """Refine ``start`` by LM (:func:`kernels.levenberg_marquardt`) with or without a drift, judged, and the
        other where the first leaves it in doubt; the criterion picks. A drift the data do not need costs the
        modes' decay and frequency their precision (it trades against a slow decay and a fraction of a cycle).

        Without a drift first (the usual window), the drift is tried where its Gauss-Newton step from there is
        over ``_DRIFT_TEST`` standard errors or a mode turns under ``_SWING_CYCLES`` (a slow swing standing in for
        a drift); with one first (where offset and drift alone already show a drift), leaving it out is tried
        where it is within ``_DRIFT_TEST`` standard errors of 0 or a mode turns under ``_SWING_CYCLES``."""
        if drift_first:
            with_drift = self.fit_as(order, start, True)
            t = t_quantile(max(self.n.size - start.size, 1), self.settings.confidence)
            evident = abs(with_drift.params[1]) * t >= _DRIFT_TEST * with_drift.half_width[1]
            if evident and not _slow_swing(with_drift.params, self.span):
                return with_drift
            start = with_drift.params
        without = self.fit_as(order, start, False)
        if drift_first:
            return min(without, with_drift, key=lambda f: f.bic)
        slow = _slow_swing(without.params, self.span)
        if not slow and kernels.step_z(self.n, self.y, self.scale, self.robust, without.params, 1) < _DRIFT_TEST:
            return without
        with_drift = self.fit_as(order, without.params, True)
        return min(without, with_drift, key=lambda f: f.bic)

    def fit_as(self, order: int, start: np.ndarray, drift: bool) -> _OrderFit:
        """Refine ``start`` by LM with the drift free, or (not ``drift``) held at 0 with the offset taking its mean,
        judged: one search of the two :meth:`fit` may make."""
        free = np.ones(start.size, dtype=np.bool_)
        if not drift:
            start = start.copy()
            start[0] += start[1] * self.mean_n
            start[1] = 0.0
            free[1] = False
        return self._judge(order, self._refine(start, free), drift=drift)

    def _refine(self, start: np.ndarray, free: np.ndarray) -> np.ndarray:
        """The LM optimum from ``start`` over the ``free`` parameters, its modes in canonical form
        (:func:`kernels.canonical`)."""
        return kernels.canonical(
            kernels.levenberg_marquardt(
                self.n,
                self.y,
                self.scale,
                self.robust,
                start,
                _LM_TOLERANCE,
                _LM_EVALUATIONS * (start.size + 1),
                free,
                _MAX_DECAY,
            )
        )

    def pinned(self, poles: _OrderFit) -> _OrderFit:
        """This window fitted with another series' poles (each mode's w and g, and their intervals): offset,
        drift and each mode's (a, b) by IRLS."""
        params = poles.params.copy()
        linear = _LINEAR[poles.order]
        _, design = kernels.columns(self.n, params)
        params[linear], cost = self.linear_fit(np.ascontiguousarray(design[:, linear]))
        _, j = kernels.weighted_jacobian(self.n, self.y, self.scale, self.robust, params)
        n, k = self.n.size, params.size
        half = poles.half_width.copy()
        variance = kernels.covariance_diagonal(np.ascontiguousarray(j[:, linear])) * cost / max(n - k, 1)
        half[linear] = t_quantile(max(n - k, 1), self.settings.confidence) * np.sqrt(variance)
        return _OrderFit(poles.order, params, half, cost, self.bic(cost, k), None, "frames")

    def _judge(self, order: int, params: np.ndarray, drift: bool = True) -> _OrderFit:
        """Cost, BIC, CI half-widths and (for modes) whether they are resolved; without ``drift`` its parameter
        (held at 0) is neither counted nor given an interval."""
        n, k = self.n.size, params.size - (not drift)
        t = t_quantile(n - k, self.settings.confidence)
        # a singular Jacobian's infinite variance: the mode is judged unresolved
        cost, half = kernels.judged(self.n, self.y, self.scale, self.robust, params, drift, t)
        return _OrderFit(
            order,
            params,
            half,
            cost,
            self.bic(cost, k),
            _unresolved(params, half, self.span),
            drift=drift,
        )


def _slow_swing(params: np.ndarray, span: float) -> bool:
    """Whether a mode of ``params`` turns less than ``_SWING_CYCLES`` over ``span`` samples: with a drift beside
    it, it may be a slower swing made into a cycle, or a swing standing in for a drift."""
    turns = 2 * np.pi * _SWING_CYCLES / float(span)  # w < this, not w * span: a huge w would overflow the product
    return any(w < turns for w in params[_BASE + 2 :: _PER_MODE].tolist())


def _unresolved(params: np.ndarray, half: np.ndarray, span: float) -> str | None:
    """Why the modes of a fit over ``span`` samples are not resolved oscillations, or None when they all are."""
    return None if _resolved(params.tolist(), half.tolist(), span) else _problems(params, half, span)


def _problems(params: np.ndarray, half: np.ndarray, span: float) -> str | None:
    """:func:`_unresolved`'s message: each mode's problem, dominant first."""
    modes = params[_BASE:].reshape(-1, _PER_MODE)
    halves = half[_BASE:].reshape(-1, _PER_MODE)
    problems = []
    for k in np.argsort(modes[:, 3], kind="stable"):  # dominant first, as reported
        w, g = modes[k, 2], modes[k, 3]
        if not np.all(np.isfinite(halves[k])):
            problems.append(f"mode at {w / (2 * np.pi):.3g} cycles/frame is not identifiable (singular Jacobian)")
        elif w * span / (2 * np.pi) < _MIN_CYCLES:
            problems.append(
                f"mode at {w / (2 * np.pi):.3g} cycles/frame turns only {w * span / (2 * np.pi):.2g} "
                f"cycles in the window (fewer than {_MIN_CYCLES}): a slow swing, not a frequency"
            )
        elif g > _MAX_DECAY:
            problems.append(f"mode at {w / (2 * np.pi):.3g} cycles/frame dies within a frame (decay {g:.3g}/frame)")
        elif (w - halves[k, 2]) * span / (2 * np.pi) < _MIN_CYCLES:
            problems.append(
                f"mode at {w / (2 * np.pi):.3g} cycles/frame: its frequency CI reaches below {_MIN_CYCLES} cycles "
                "in the window (it may be a slow swing, not a frequency)"
            )
    return "; ".join(problems) or None


def _resolved(params: list[float], half: list[float], span: float) -> bool:
    """Whether :func:`_unresolved` finds nothing wrong with any mode: its tests in plain floats, each mode once
    (numpy's per-call cost on a few values was most of a fit's judging in Python)."""
    for j in range(_BASE, len(params), _PER_MODE):
        w, g = params[j + 2], params[j + 3]
        if not (
            all(math.isfinite(h) for h in half[j : j + _PER_MODE])
            and not w * span / (2 * np.pi) < _MIN_CYCLES
            and not g > _MAX_DECAY
            and not (w - half[j + 2]) * span / (2 * np.pi) < _MIN_CYCLES
        ):
            return False
    return True


def _evidence(fit: _OrderFit) -> float:
    """BIC with each mode asked to gain ``_EVIDENCE`` more: the ordering :func:`_choose` picks by."""
    return fit.bic + _EVIDENCE * fit.order


def _choose(fits: list[_OrderFit]) -> tuple[_OrderFit, str | None]:
    """The BIC choice; where it is unresolved, the best resolved fit of fewer modes (order 0 at least): a fit of
    more modes is no way out, for its extra mode resolves only by making one up (a slow swing turned into a
    cycle beside a mode fitting the noise)."""
    best = min(fits, key=_evidence)
    if best.problem is None:
        return best, None
    resolved = min((f for f in fits if f.problem is None and f.order < best.order), key=_evidence)
    if resolved.order > 0:
        return resolved, f"the {best.order}-mode fit was better but unresolved ({best.problem})"
    return best, best.problem


def fit_window(
    values: ArrayLike,
    fps: float,
    settings: FitSettings = FitSettings(),
    *,
    index: int = 0,
    start_frame: int = 0,
    starts_at_ejection: bool = False,
    ends_at_ejection: bool = False,
    brightness: ArrayLike | None = None,
) -> WindowResult:
    """Fit one window of the centre displacement and judge it (ok, settled, unresolved or failed).

    Parameters
    ----------
    values : array of shape (N,), mm, one per frame from the window start; NaN/Inf are missing samples.
        A window that starts at an ejection has its first ``settings.transient_frames(fps)`` left out.
    fps : frames per second (frame i is at t = i / fps).
    settings : model orders, loss, confidence level and settling tolerance.
    brightness : array of shape (N,), the window's mean frame brightness (any unit, NaN missing): with
        ``settings.poles == "frames"`` the modes' frequencies and decay rates are those of its fit when it
        resolves an oscillation (as damped modes, or by default as a polynomial of two modes:
        ``settings.brightness_model``), and the series gives their amplitudes and phases, the offset and the drift.

    Returns
    -------
    WindowResult with modes in mm, Hz, 1/s, rad (dominant, i.e. smallest decay rate, first).
    """
    with blas.threads(1):  # small matrices: a multi-threaded BLAS made a window 7x slower on a loaded 2-core machine
        return _fit_window(values, fps, settings, index, start_frame, starts_at_ejection, ends_at_ejection, brightness)


def _fit_window(
    values: ArrayLike,
    fps: float,
    settings: FitSettings,
    index: int,
    start_frame: int,
    starts_at_ejection: bool,
    ends_at_ejection: bool,
    brightness: ArrayLike | None,
) -> WindowResult:
    """:func:`fit_window` on the calling thread's BLAS settings."""
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    missing = int(x.size - np.isfinite(x).sum())
    skip = min(settings.transient_frames(fps), x.size) if starts_at_ejection else 0
    x = _after_transient(x, skip)
    finite = np.isfinite(x)
    common = dict(
        index=index,
        start_frame=start_frame,
        end_frame=start_frame + x.size,
        samples=int(finite.sum()),
        missing=missing,
        transient_frames=skip,
        starts_at_ejection=starts_at_ejection,
        ends_at_ejection=ends_at_ejection,
    )
    need = min_samples(min(1, settings.max_modes))
    if finite.sum() < need:
        return WindowResult(
            status="failed",
            **common,
            reason=f"{int(finite.sum())} finite samples of {x.size}; testing for an oscillation needs {need}",
        )
    largest = float(np.max(np.abs(x[finite])))
    if largest > _MAX_VALUE:
        return WindowResult(
            status="failed",
            **common,
            reason=f"values up to {largest:.3g}: beyond {_MAX_VALUE:.0e} "
            "the fit's sums of squares would overflow (a unit or a corrupt sample?)",
        )
    n, raw, centre, spread = _centred(x)
    if spread <= 8 * np.finfo(float).eps * max(abs(centre), np.finfo(float).tiny):
        return WindowResult(
            status="settled",
            reason="constant series: no oscillation (r2 undefined)",
            **common,
            offset_mm=centre,
            drift_mm_per_s=0.0,
            settling_time_s=0.0,
            settled=True,
            residual_amplitude_mm=0.0,
            noise_mm=0.0,
        )
    window = _Window(n, (raw - centre) / spread, settings)
    use_frames = settings.poles == "frames" and brightness is not None
    later = settings.brightness_frames(fps) if starts_at_ejection else 0
    poles = _brightness_poles(brightness, x.size, skip, later, settings, window) if use_frames else None
    if poles is not None:
        chosen, problem = _fundamental(window, poles)
    else:
        fits = _order_fits(window, x.size, settings)
        outliers = _outliers(window, fits)
        if outliers.any():  # fitted again without them: a spike drags the start and the order choice
            window = window.without(outliers)
            fits = _order_fits(window, x.size, settings)
        chosen, problem = _choose(fits)
        if window.robust and not outliers.any() and chosen.problem is None:
            chosen = window.polish(chosen)
        if outliers.any():
            problem = "; ".join(
                [p for p in [problem] if p]
                + [f"{int(outliers.sum())} samples left out as outliers (over {_OUTLIER:g} sd off the fit)"]
            )
    return _result(chosen, problem, window, centre, spread, fps, settings, common)


def _outliers(window: _Window, fits: list[_OrderFit]) -> np.ndarray:
    """Samples (mask over the window's finite ones) whose residual from the chosen fit (offset and drift alone
    where its modes are not resolved: one may be a spike at the start, dying within a frame) is over ``_OUTLIER``
    robust standard deviations: spikes, not the signal. When more than ``_MAX_OUTLIERS`` of the samples are that
    far off (an oscillation the fit missed, spikes or not), only those standing ``_SPIKE_GAP`` times above all the
    rest are: a spike of 20x the amplitude stands apart from any oscillation the window holds."""
    chosen, _ = _choose(fits)
    reference = chosen if chosen.problem is None else fits[0]
    model, _ = kernels.columns(window.n, reference.params)
    residual = window.y - model
    size, sigma = np.abs(residual), robust_sigma(residual)
    flagged = size > _OUTLIER * sigma
    if sigma == 0 or flagged.sum() <= _MAX_OUTLIERS * window.n.size:
        return flagged & (sigma > 0)
    top = np.sort(size)[::-1][: int(_MAX_OUTLIERS * window.n.size) + 1]  # descending
    gaps = np.flatnonzero(top[:-1] > _SPIKE_GAP * top[1:])
    return size >= top[gaps[-1]] if gaps.size else np.zeros(window.n.size, dtype=bool)


def _after_transient(x: np.ndarray, skip: int) -> np.ndarray:
    """A window's samples (N,) with the first ``skip`` (the ejection's transient) missing."""
    return np.concatenate([np.full(skip, np.nan), x[skip:]])


def _centred(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The finite samples of ``x`` (N,): their indices (as floats), values, median and largest deviation from it."""
    finite = np.isfinite(x)
    raw = x[finite]
    centre = kernels.median(raw)
    return np.flatnonzero(finite).astype(np.float64), raw, centre, float(np.max(np.abs(raw - centre)))


def _order_fits(
    window: _Window,
    length: int,
    settings: FitSettings,
    drift_of_one: bool = False,
    max_modes: int | None = None,
    fewer: list[_OrderFit] | None = None,
) -> list[_OrderFit]:
    """The fit of each model order (0 to ``settings.max_modes``, or ``max_modes`` where fewer) a window ``length``
    frames long can take, those of the lower orders in ``fewer`` (this function's, order 0 first) kept; with
    ``drift_of_one``, two modes are searched from the pencil with the drift the one-mode fit chose, not with both
    (the brightness' search, whose poles alone are wanted; what it saves: docs/benchmarks.md)."""
    fits = list(fewer or [window.fit_baseline()])
    most = settings.max_modes if max_modes is None else min(max_modes, settings.max_modes)
    orders = [m for m in range(1, most + 1) if window.n.size >= min_samples(m)]
    if orders:
        poles = 2 * orders[-1] + 2
        starts = [_pencil_modes(window.n, window.y, length, poles)]
        run = _strongest_run(window.n, window.y, 3 * poles)
        if run is not None:  # gaps: their linear filling misleads the pencil, which a gap-free stretch does not
            starts.append(_pencil_modes(window.n[run] - window.n[run[0]], window.y[run], run.size, poles))
        for m in orders[len(fits) - 1 :]:
            if drift_of_one and m >= 2:  # fits[-1] is the fit of m - 1 modes
                searches = (window.fit_as(m, window.starts(m, modes), fits[-1].drift) for modes in starts)
            else:
                searches = (window.fit(m, window.starts(m, modes), fits[0].drift) for modes in starts)
            fit = min(searches, key=lambda f: f.cost)
            if fit.problem is not None and m == 1:  # a short window's most energetic pencil pair may be a spurious one
                for w, g in starts:
                    for i in range(1, w.size):
                        other = window.fit(1, window.starts(1, (w[i : i + 1], g[i : i + 1])), fits[0].drift)
                        fit = min(fit, other, key=lambda f: f.cost)
            if fit.problem is not None and fits[-1].order == m - 1 >= 1:
                extended = window.extended(fits[-1], length)
                if extended is not None:
                    fit = min(fit, window.fit(m, extended, fits[0].drift), key=lambda f: f.cost)
            fits.append(fit)
    return fits


def _strongest_run(n: np.ndarray, y: np.ndarray, shortest: int) -> np.ndarray | None:
    """Indices of the gap-free stretch of consecutive samples with the most variance about its mean (at least
    ``shortest`` samples), when the samples ``n`` (ascending whole indices) have gaps; None without gaps or such a
    stretch."""
    if n.size == 0 or n[-1] - n[0] == n.size - 1:  # no gap: the usual window, without looking at each step
        return None
    breaks = np.flatnonzero(np.diff(n) != 1) + 1
    if breaks.size == 0:
        return None
    runs = [r for r in np.split(np.arange(n.size), breaks) if r.size >= shortest]
    return max(runs, key=lambda r: float(np.var(y[r]) * r.size), default=None)


def _has_harmonic(fit: _OrderFit) -> bool:
    """Whether a mode of ``fit`` sits at twice another's frequency (within their intervals): brightness is not
    linear in the surface's height, so a strong mode also brightens at its second harmonic, which is no mode
    of the surface (Eq. 1's second mode lies at l2 / l1 = 2.30 times the first)."""
    w = fit.params[_BASE + 2 :: _PER_MODE]
    half = fit.half_width[_BASE + 2 :: _PER_MODE]
    return any(abs(w[j] - 2 * w[i]) <= half[j] + 2 * half[i] for i in range(w.size) for j in range(w.size) if i != j)


def _brightness_poles(
    brightness: ArrayLike, length: int, skip: int, later: int, settings: FitSettings, series: _Window
) -> _OrderFit | None:
    """The fit of a window's mean frame brightness (``length`` values, NaN missing; its first ``skip`` left out, and
    its first ``later`` out of the polynomial's fit) when it resolves an oscillation: its modes' w and g are the
    poles the window's ``series`` is fitted with. None when it does not (as damped modes, nor, with the polynomial,
    from its strongest line where the series confirms it: :func:`_line_poles`)."""
    x = np.asarray(brightness, dtype=np.float64).reshape(-1)
    if x.size != length:
        raise ValueError(f"{x.size} brightness values for a window of {length} frames")
    x = _after_transient(x, skip)
    if np.isfinite(x).sum() < min_samples(1) or settings.max_modes == 0:
        return None
    n, raw, centre, spread = _centred(x)
    if not 0 < spread < _MAX_VALUE:
        return None
    y = (raw - centre) / spread
    # the polynomial takes only its start from the damped modes (its modes are its own): their one-mode fit
    # where it resolves an oscillation, else their two-mode search's (the one mode may be the ejection's light, dying
    # within a cycle, beside a heavily damped mode); the damped modes' own poles are those of their order search
    window = _Window(n, y, settings)
    fits = chosen = None
    if settings.brightness_model == "products":
        fits = _order_fits(window, x.size, settings, max_modes=1)
        chosen, _ = _choose(fits)
    if chosen is None or chosen.order == 0 or chosen.problem is not None or _underdamped(chosen).size == 0:
        fits = _order_fits(window, x.size, settings, drift_of_one=True, fewer=fits)
        chosen, _ = _choose([f for f in fits if not _has_harmonic(f)])  # resolved, if a higher order was not
    kept = n >= later  # the polynomial's fit starts later: the ejection's light is no function of the modes
    if chosen.order == 0 or chosen.problem is not None:
        if settings.brightness_model == "modes":
            return None
        poles = _line_poles(n[kept], y[kept], fits[0], settings, series)  # fits[0]: the brightness' order 0
    elif settings.brightness_model == "modes":
        poles = chosen
    else:
        poles = _product_poles(n[kept], y[kept], chosen, settings)
    poles = None if poles is None else _oscillations(poles)
    return None if poles is None else _fundamental_alone(poles)


def _fundamental_alone(fit: _OrderFit) -> _OrderFit:
    """``fit`` with its lower mode alone where its higher one, :data:`_HARMONIC_RATIO` times its frequency, decays
    slower: the brightness' fit may end with the second harmonic beside the mode itself (the polynomial's, started
    from a brightness whose strongest pole was the harmonic), and the harmonic would be reported as the dominant
    mode. Eq. 1's second mode lies 2.30 times the first's frequency and decays faster."""
    w, g = fit.params[_BASE + 2 :: _PER_MODE], fit.params[_BASE + 3 :: _PER_MODE]
    if fit.order < 2 or not (
        _HARMONIC_RATIO[0] < w.max() / w.min() < _HARMONIC_RATIO[1] and g[np.argmax(w)] < g[np.argmin(w)]
    ):
        return fit
    return _with_modes(fit, np.array([np.argmin(w)]))


def _fundamental(window: _Window, poles: _OrderFit) -> tuple[_OrderFit, str | None]:
    """``window`` fitted with the brightness' ``poles``, or with their lowest mode at half its frequency and decay
    rate where that fits the series far better (cost under :data:`_HALVED_GAIN` times) and is still resolved (the
    amplitudes' intervals the series' own), with the note that says so. A highlight that sweeps across the surface
    and back brightens twice a cycle: the brightness may then hold a mode only at its second harmonic, which turns
    and decays twice as fast."""
    pinned = window.pinned(poles)
    at = _BASE + _PER_MODE * int(np.argmin(poles.params[_BASE + 2 :: _PER_MODE])) + 2
    params, half = poles.params.copy(), pinned.half_width.copy()
    params[at : at + 2] /= 2
    half[at : at + 2] /= 2
    if not _resolved(params.tolist(), half.tolist(), window.span):
        return pinned, None
    halved = window.pinned(replace(poles, params=params, half_width=half))
    if not halved.cost < _HALVED_GAIN * pinned.cost:
        return pinned, None
    hz = params[at] / (2 * np.pi)
    return halved, (
        f"the frames' brightness turned at twice the series' {hz:.3g} cycles/frame (a highlight brightening twice "
        "a cycle): its mode halved"
    )


def _oscillations(fit: _OrderFit) -> _OrderFit | None:
    """``fit`` with only its underdamped modes (decaying by e over more than :data:`_UNDERDAMPED` radians), the
    poles handed to the window's series; None when none is left. The brightness' fit may spend a pole on the
    ejection's light dying within a fraction of a cycle: that is no oscillation of the surface, and a series
    fitted with it extrapolates to its start through many e-folds (amplitudes far beyond the nozzle)."""
    keep = _underdamped(fit)
    if keep.size == fit.order:
        return fit
    if keep.size == 0:
        return None
    return _with_modes(fit, keep)


def _underdamped(fit: _OrderFit) -> np.ndarray:
    """Indices of ``fit``'s modes that decay by e over more than :data:`_UNDERDAMPED` radians: oscillations."""
    return np.flatnonzero(fit.params[_BASE + 3 :: _PER_MODE] * _UNDERDAMPED < fit.params[_BASE + 2 :: _PER_MODE])


def _with_modes(fit: _OrderFit, keep: np.ndarray) -> _OrderFit:
    """``fit`` with only its modes ``keep`` (indices), offset and drift as they are."""
    columns = np.r_[np.arange(_BASE), (_BASE + _PER_MODE * keep[:, None] + np.arange(_PER_MODE)).ravel()]
    return replace(fit, order=int(keep.size), params=fit.params[columns], half_width=fit.half_width[columns])


def _product_poles(n: np.ndarray, y: np.ndarray, modes: _OrderFit, settings: FitSettings) -> _OrderFit:
    """The poles of the brightness fitted as a polynomial of two modes (:func:`products.fit`), started from the
    lowest-frequency underdamped mode of ``modes`` (the brightness' fit as damped modes; underdamped: decaying by e
    over more than :data:`_UNDERDAMPED` radians, for a pole that dies within a fraction of a cycle is the ejection's
    light or noise, and harmonics and sum frequencies lie above mode 1), or from the brightness' strongest line
    (:func:`_strongest_line`) where that lies elsewhere and its fit is acceptable and costs less: its mode 1 and,
    where ``settings`` allow two modes and its frequency is sharp (:data:`_SHARP`), its mode 2. ``modes`` itself
    where it has no such mode or the fit kept is not acceptable (:func:`_acceptable`)."""
    under = _underdamped(modes)
    if under.size == 0:
        return modes
    frequencies = modes.params[_BASE + 2 :: _PER_MODE]
    first = int(under[np.argmin(frequencies[under])])
    w, g = float(frequencies[first]), float(modes.params[_BASE + _PER_MODE * first + 3])
    found = products.fit(n, y, w, g, settings.confidence)
    line = _strongest_line(n, y)
    if line is not None and abs(line - w) > _PRODUCT_SHIFT * w:
        other = products.fit(n, y, line, _LINE_DECAY * line, settings.confidence)
        if _acceptable(other, line) and (found is None or other.cost < found.cost):
            found, w = other, line
    return _poles_of(found, modes, settings) if _acceptable(found, w) else modes


def _line_poles(
    n: np.ndarray, y: np.ndarray, baseline: _OrderFit, settings: FitSettings, series: _Window
) -> _OrderFit | None:
    """Where the brightness' damped fits resolve no oscillation: the poles of its polynomial of two modes started
    from its strongest line (:func:`_strongest_line`), where that fit is acceptable, its mode 1's frequency sharp
    (:data:`_SHARP`) and the ``series`` fitted with them beats its offset and drift alone by the evidence a mode must
    bring (:data:`_EVIDENCE`: a noise-only brightness gave sharp poles too); None otherwise. A faint brightness under
    the ejection's fading light shows its mode in its spectrum where the damped fits do not, and the series' own
    poles, the alternative, read the decay far off (docs/benchmarks.md, "The brightness polynomial's poles not held to
    their start")."""
    line = _strongest_line(n, y)
    if line is None:
        return None
    found = products.fit(n, y, line, _LINE_DECAY * line, settings.confidence)
    if not _acceptable(found, line) or found.w_half[0] > _SHARP * found.w[0]:
        return None
    poles = _poles_of(found, baseline, settings)
    return poles if _evidence(series.pinned(poles)) < _evidence(series.fit_baseline()) else None


def _poles_of(found: products.ProductFit, fit: _OrderFit, settings: FitSettings) -> _OrderFit:
    """``fit`` with the polynomial's poles alone (the series refits the offset, drift and amplitudes:
    :meth:`_Window.pinned`): its mode 1 and, where ``settings`` allow two modes and its frequency is sharp
    (:data:`_SHARP`), its mode 2."""
    order = 2 if settings.max_modes >= 2 and found.w_half[1] <= _SHARP * found.w[1] else 1
    params, half = np.zeros(_BASE + _PER_MODE * order), np.full(_BASE + _PER_MODE * order, np.inf)
    for k in range(order):
        at = _BASE + _PER_MODE * k
        params[at + 2 : at + 4] = found.w[k], found.g[k]
        half[at + 2 : at + 4] = found.w_half[k], found.g_half[k]
    return replace(fit, order=order, params=params, half_width=half)


def _acceptable(found: products.ProductFit | None, w: float) -> bool:
    """Whether the polynomial fitted from mode 1 at ``w`` converged near it: not on another mode (frequency within
    :data:`_PRODUCT_SHIFT`), with a mode 1 that is an oscillation (underdamped) and mode 2 more damped than mode 1
    (Eq. 1's higher mode damps faster: else it has taken something else for it)."""
    return (
        found is not None
        and abs(found.w[0] - w) <= _PRODUCT_SHIFT * w
        and found.g[0] * _UNDERDAMPED < found.w[0]
        and found.g[1] > found.g[0]
    )


def _strongest_line(n: np.ndarray, y: np.ndarray) -> float | None:
    """The frequency (radians per sample) of the highest peak of the gap-filled, detrended series' spectrum (Hann
    window, zero-padded to a power of two at least 4 times its length: a start for a fit, to a few % of it) between
    :data:`_LINE_CYCLES` cycles over the window and 0.9 pi; None where the window is too short to hold that many."""
    grid = np.arange(n[0], n[-1] + 1, dtype=np.float64)
    padded = 1 << int(np.ceil(np.log2(4 * grid.size)))  # a power of two: the FFT's fastest length
    lowest = int(_LINE_CYCLES * padded / grid.size) + 1  # bin k is at w = 2 pi k / padded
    above = int(np.ceil(0.45 * padded))  # the first bin at 0.9 pi or over
    if lowest >= above:
        return None
    spectrum = np.fft.rfft(_detrended(grid, n, y) * _hann(grid.size), padded)[lowest:above]
    return 2 * np.pi * (lowest + int(np.argmax(np.abs(spectrum)))) / padded


@functools.lru_cache(maxsize=8)
def _hann(size: int) -> np.ndarray:
    """The Hann window of ``size`` samples, read-only (windows come in a few lengths: made once each)."""
    window = np.hanning(size)
    window.flags.writeable = False
    return window


def _pencil_modes(n: np.ndarray, y: np.ndarray, length: int, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Pencil pole pairs (w, g per sample, most energetic first) of the gap-filled, detrended series."""
    filled = _detrended(np.arange(length, dtype=np.float64), n, y)
    return pencil.damped_sinusoids(filled, min(max(_PENCIL, order), length // 3), order, _PENCIL_MIN_CYCLES)


def _detrended(grid: np.ndarray, n: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The series ``y`` at samples ``n`` interpolated onto ``grid`` (its gaps filled), less its least-squares line."""
    filled = np.interp(grid, n, y)
    centred = grid - grid.mean()
    filled -= filled.mean() + centred * (centred @ filled) / (centred @ centred)
    return filled


def _result(
    fit: _OrderFit,
    problem: str | None,
    window: _Window,
    centre: float,
    spread: float,
    fps: float,
    settings: FitSettings,
    common: dict,
) -> WindowResult:
    """Back to mm, Hz and 1/s; the status, the settling metrics and r2 of the chosen fit."""
    model, _ = kernels.columns(window.n, fit.params)
    ss_res = float(np.sum((window.y - model) ** 2))
    ss_tot = float(np.sum((window.y - window.y.mean()) ** 2))
    offset = centre + spread * fit.params[0]
    numbers = dict(
        offset_mm=offset,
        offset_ci_mm=(offset - spread * fit.half_width[0], offset + spread * fit.half_width[0]),
        intervals="fit",
        drift_mm_per_s=spread * fit.params[1] * fps,
        r2=1.0 - ss_res / ss_tot if ss_tot > 0 else float("nan"),  # nan: all samples left equal (null, reason says)
        noise_mm=spread * robust_sigma(window.y - model),
    )
    if fit.order == 0:
        return _without_modes(fit, problem, window, spread, settings, common, numbers)
    modes = fit.params[_BASE:].reshape(-1, _PER_MODE)
    halves = fit.half_width[_BASE:].reshape(-1, _PER_MODE)
    order = np.lexsort((-np.hypot(modes[:, 0], modes[:, 1]), modes[:, 3]))  # decay up, then amplitude down
    modes, halves = modes[order], halves[order]
    a, b, w, g = modes.T
    hz, per_s = fps / (2 * np.pi), fps
    f, decay, amp = w * hz, g * per_s, spread * np.hypot(a, b)
    f_half, g_half = halves[:, 2] * hz, halves[:, 3] * per_s
    # the amplitude's by the delta method on hypot(a, b) (a and b taken as independent: the diagonal is what the
    # fit keeps); at a = b = 0 its gradient is undefined, and the larger of their intervals stands in
    r, spread_ab = np.hypot(a, b), np.hypot(a * halves[:, 0], b * halves[:, 1])
    a_half = spread * np.where(r > 0, spread_ab / np.where(r > 0, r, 1.0), np.maximum(halves[:, 0], halves[:, 1]))
    zeta, q = damping_ratio(f, decay), quality_factor(f, decay)
    estimates = [
        dict(
            frequency_hz=f[k],
            decay_rate_per_s=decay[k],
            amplitude_mm=amp[k],
            phase_rad=float(np.arctan2(-b[k], a[k])),
            frequency_ci_hz=(max(f[k] - f_half[k], 0.0), min(f[k] + f_half[k], fps / 2)),
            decay_rate_ci_per_s=(max(decay[k] - g_half[k], 0.0), decay[k] + g_half[k]),
            amplitude_ci_mm=(max(amp[k] - a_half[k], 0.0), amp[k] + a_half[k]),
            damping_ratio=zeta[k],
            quality_factor=q[k],
        )
        for k in range(len(order))
    ]
    duration = (common["end_frame"] - common["start_frame"]) / fps
    s = settle(amp, decay, duration, settings.settle_fraction, settings.settle_floor_mm)
    status = "unresolved" if fit.problem else "ok"
    problem = problem or fit.problem  # a polished or pinned fit's own, where the choice between orders had none
    if not s.settled:
        problem = "; ".join([p for p in [problem] if p] + [_still_running(s, common["ends_at_ejection"])])
    return WindowResult(
        status=status,
        reason=problem,
        **common,
        **numbers,
        modes=estimates,
        poles_from=fit.poles_from,
        settling_time_s=s.time_s,
        settled=s.settled,
        residual_amplitude_mm=s.residual_amplitude_mm,
    )


def _still_running(s: Settling, at_ejection: bool) -> str:
    """What a window whose oscillation had not settled when it ended says of it."""
    end = "the next ejection" if at_ejection else "the end of the window"
    return (
        f"still oscillating at {end}: residual amplitude {s.residual_amplitude_mm:.3g} mm over the settling "
        f"tolerance {s.tolerance_mm:.3g} mm"
    )


def _without_modes(
    fit: _OrderFit,
    problem: str | None,
    window: _Window,
    spread: float,
    settings: FitSettings,
    common: dict,
    numbers: dict,
) -> WindowResult:
    """Order 0 chosen: settled, unless the displacement trends (evidently, and beyond the settling tolerance)."""
    note = f" ({problem})" if problem else ""
    change = spread * abs(fit.params[1]) * (window.n[-1] - window.n[0])  # mm over the window
    tol = tolerance([], settings.settle_fraction, settings.settle_floor_mm)
    if change > tol and fit.drift:
        return WindowResult(
            status="unresolved",
            **common,
            **numbers,
            residual_amplitude_mm=None,
            reason=f"no resolved oscillation, but the displacement trends by {change:.3g} mm over the window "
            f"(settling tolerance {tol:.3g} mm): a slow motion under one cycle, or drift{note}",
        )
    model, _ = kernels.columns(window.n, fit.params)
    residual = spread * np.sqrt(2 * np.mean((window.y - model) ** 2))
    alone = "offset and drift" if fit.drift else "an offset"
    return WindowResult(
        status="settled",
        **common,
        **numbers,
        settling_time_s=0.0,
        settled=True,
        residual_amplitude_mm=residual,
        reason=f"settled: no oscillation above the noise ({settings.criterion} prefers {alone} alone; what is left "
        f"moves {residual:.3g} mm, the amplitude of a sinusoid of its power){note}",
    )


def model_curve(result: WindowResult, t: ArrayLike) -> np.ndarray:
    """The fitted centre displacement (mm) at ``t`` s since the window start; NaN for a failed window."""
    t = np.asarray(t, dtype=np.float64)
    if result.offset_mm is None:
        return np.full(t.shape, np.nan)
    curve = result.offset_mm + (result.drift_mm_per_s or 0.0) * t
    for m in result.modes:
        curve = curve + damped_mode(t, m.amplitude_mm, m.decay_rate_per_s, m.frequency_hz, m.phase_rad)
    return curve


def warm() -> None:
    """Compile the fit's kernels (or load them from numba's cache) on a small window of each loss, so that the
    first real window does not wait for the compiler (~15 s uncached on two cores, ~0.5 s from the cache)."""
    t = np.arange(64) / 19000.0
    y = damped_mode(t, 0.01, 300.0, 1500.0, 0.3) + damped_mode(t, 0.004, 900.0, 3900.0, 1.0)
    for loss in ("soft_l1", "linear"):
        fit_window(y, 19000.0, FitSettings(loss=loss), brightness=y + y**2)  # the brightness' polynomial fit too


def fit_windows(
    series: ArrayLike,
    fps: float,
    windows: Sequence[Window],
    settings: FitSettings = FitSettings(),
    progress: bool = True,
    brightness: ArrayLike | None = None,
) -> list[WindowResult]:
    """One window fit per window of ``series`` (mm per frame), as every front door runs it
    (:func:`service.pipeline.windows.fit_job`), with a progress bar over windows; ``brightness`` (same shape, the
    frames' mean brightness) as :func:`fit_window` takes it."""
    from service.pipeline.windows import WindowJob, fit_job  # the pipeline's job calls this module's fit_window

    x = np.asarray(series, dtype=np.float64).reshape(-1)
    b = None if brightness is None else np.asarray(brightness, dtype=np.float64).reshape(-1)
    return [
        fit_job(WindowJob(w, x[w.start : w.end], None if b is None else b[w.start : w.end]), fps, settings)
        for w in tqdm(windows, desc="fit", unit="window", disable=not progress)
    ]
