"""The window-fit suite: seeded windows in every category the fit meets at its extremes, each method scored on them
against the truth and against the Cramer-Rao bound of the true model.

A window is ``c + v t + sum_k A_k exp(-g_k t) cos(2 pi f_k t + phi_k)`` sampled at 19,000 frames/s (190 frames
unless the category says otherwise) plus white Gaussian noise of standard deviation ``A_1 / SNR``, and whatever the
category adds (spikes, NaN runs, a drift, a scale). A method's answer is the list of modes it reports (ours: only
when its status is ``ok``). Scores:

- **ok**: every true mode is matched by a reported one with frequency within 1 % and decay rate within 20 % (of
  the true rate, or of one e-fold per window for a mode that barely decays: 20 % of 0 would ask for exactness).
  Where there is no mode to find (pure noise, constants), ok means reporting none; any reported mode is a false
  detection. Under 0.8 cycles ok means honest: no mode reported, or the true one (never a made-up frequency).
- **efficiency**: where the model is exact (white Gaussian noise, no spikes or gaps), median over windows of
  |error| / (CRB standard deviation) for the dominant mode's frequency and decay, divided by 0.674 (the median
  of |z| for a standard normal): 1.0 is an efficient, unbiased estimator.
- **coverage**: share of those windows whose 95 % interval holds the true frequency (decay), for methods with
  intervals.

The CRB is the inverse of the Fisher information ``J'J / sigma^2`` of the true model's parameters (offset, the
drift where the category has one, and ``a, b, w, g`` per mode) at the true values, over the finite samples.
"""

from __future__ import annotations

import resource
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from tqdm import tqdm

from service.analysis import kernels
from service.analysis.fit import fit_window
from service.bench.peers import Found, available, curve_fit_found, harminv_found, pencil_found

FPS, FRAMES = 19000.0, 190
AMPLITUDE_MM = 0.01  # of the dominant mode (before a scale category multiplies everything)
F_TOL, G_TOL = 0.01, 0.20  # "ok": relative frequency and decay-rate tolerance
MEDIAN_ABS_NORMAL = 0.6744897501960817


@dataclass
class Window:
    """One suite window: its series (mm, NaN missing) and what generated it."""

    category: str
    values: np.ndarray
    modes: list[tuple[float, float, float, float]]  # (A mm, g 1/s, f Hz, phi rad), dominant first
    sigma: float  # noise standard deviation (mm)
    offset: float = 0.0
    drift: float = 0.0  # mm per frame
    exact: bool = True  # white Gaussian noise on the model alone: the CRB applies
    honest_only: bool = False  # under 0.8 cycles: only an honest answer is asked for


@dataclass
class Category:
    """How one category's windows are drawn."""

    name: str
    draw: Callable[[np.random.Generator], Window]
    notes: str = ""


def _series(
    rng: np.random.Generator,
    modes: list[tuple[float, float, float, float]],
    n: int,
    snr: float,
    offset: float = 0.0,
    drift: float = 0.0,
) -> tuple[np.ndarray, float]:
    """The model at (A, g, f, phi) modes over n frames, plus noise at A_1 / snr (none for snr = inf)."""
    t = np.arange(n) / FPS
    y = (
        offset
        + drift * np.arange(n)
        + sum((a * np.exp(-g * t) * np.cos(2 * np.pi * f * t + p) for a, g, f, p in modes), np.zeros(n))
    )
    sigma = 0.0 if not np.isfinite(snr) else modes[0][0] / snr if modes else AMPLITUDE_MM / snr
    return y + rng.normal(0.0, sigma, n) if sigma else y, sigma


def _mode(
    rng: np.random.Generator,
    f: tuple[float, float] = (600.0, 3000.0),
    g: tuple[float, float] = (100.0, 600.0),
    a: float = AMPLITUDE_MM,
) -> tuple[float, float, float, float]:
    """One mode with frequency (Hz) and decay (1/s) drawn uniformly from the ranges, a random phase."""
    return a, rng.uniform(*g), rng.uniform(*f), rng.uniform(-np.pi, np.pi)


def _simple(
    name: str,
    snr: float,
    n: int | tuple[int, int] = FRAMES,
    offset: float = 0.0,
    drift_per_window: float = 0.0,
    scale: float = 1.0,
    **mode,
) -> Callable[[np.random.Generator], Window]:
    """A single-mode category: the mode from ``mode``'s ranges, noise at ``snr``, an offset and a drift (total
    change over the window, in dominant amplitudes), everything times ``scale``."""

    def draw(rng: np.random.Generator) -> Window:
        size = n if isinstance(n, int) else int(rng.integers(n[0], n[1] + 1))
        modes = [_mode(rng, **mode)]
        drift = drift_per_window * AMPLITUDE_MM * rng.choice([-1, 1]) / size
        y, sigma = _series(rng, modes, size, snr, offset, drift)
        scaled = [(a * scale, g, f, p) for a, g, f, p in modes]
        return Window(name, y * scale, scaled, sigma * scale, offset * scale, drift * scale)

    return draw


def _two(
    name: str, ratio: tuple[float, float], amplitude: tuple[float, float], decay: tuple[float, float], snr: float
) -> Callable[[np.random.Generator], Window]:
    """Two modes: the second at ``ratio`` times the first's frequency, ``amplitude`` times its amplitude and
    ``decay`` times its decay rate (each drawn uniformly)."""

    def draw(rng: np.random.Generator) -> Window:
        first = _mode(rng)
        second = (
            first[0] * rng.uniform(*amplitude),
            first[1] * rng.uniform(*decay),
            first[2] * rng.uniform(*ratio),
            rng.uniform(-np.pi, np.pi),
        )
        y, sigma = _series(rng, [first, second], FRAMES, snr)
        return Window(name, y, [first, second], sigma)

    return draw


def _heavy(rng: np.random.Generator) -> Window:
    """1-3 visible cycles: the envelope falls to 5 % (3 e-folds) within that many periods."""
    f = rng.uniform(600.0, 3000.0)
    visible = rng.uniform(1.0, 3.0)
    modes = [(AMPLITUDE_MM, 3.0 * f / visible, f, rng.uniform(-np.pi, np.pi))]
    y, sigma = _series(rng, modes, FRAMES, 100.0)
    return Window("heavy damping (1-3 visible cycles)", y, modes, sigma)


def _cycles(name: str, low: float, high: float, honest_only: bool) -> Callable[[np.random.Generator], Window]:
    """One lightly damped mode turning ``low``-``high`` cycles over the window."""

    def draw(rng: np.random.Generator) -> Window:
        f = rng.uniform(low, high) * FPS / FRAMES
        modes = [(AMPLITUDE_MM, rng.uniform(0.0, 20.0), f, rng.uniform(-np.pi, np.pi))]
        y, sigma = _series(rng, modes, FRAMES, 50.0)
        return Window(name, y, modes, sigma, honest_only=honest_only)

    return draw


def _noise(rng: np.random.Generator) -> Window:
    """White noise alone, at a random level."""
    sigma = AMPLITUDE_MM * 10 ** rng.uniform(-3, 1)
    return Window("pure noise", rng.normal(0.0, sigma, FRAMES), [], sigma)


def _constant(rng: np.random.Generator) -> Window:
    """A constant at any magnitude (or 0), some with a last-bit rounding wobble."""
    value = rng.choice([0.0, 1.0]) * 10 ** rng.uniform(-12, 12) * rng.choice([-1, 1])
    y = np.full(FRAMES, value)
    if rng.random() < 0.5:
        y = y + value * np.finfo(float).eps * rng.integers(-2, 3, FRAMES)
    return Window("constants", y, [], 0.0, offset=value)


def _spikes(rng: np.random.Generator) -> Window:
    """A nominal window with 2-6 single-frame spikes of 20x the amplitude (either sign)."""
    modes = [_mode(rng)]
    y, sigma = _series(rng, modes, FRAMES, 50.0)
    at = rng.choice(FRAMES, int(rng.integers(2, 7)), replace=False)
    y[at] += 20 * AMPLITUDE_MM * rng.choice([-1, 1], at.size)
    return Window("spikes (20x amplitude)", y, modes, sigma, exact=False)


def _nan_runs(rng: np.random.Generator) -> Window:
    """A nominal window with 1-3 runs of 5-25 missing frames."""
    modes = [_mode(rng)]
    y, sigma = _series(rng, modes, FRAMES, 50.0)
    for _ in range(int(rng.integers(1, 4))):
        start = int(rng.integers(0, FRAMES - 25))
        y[start : start + int(rng.integers(5, 26))] = np.nan
    return Window("runs of NaN", y, modes, sigma)


CATEGORIES = [
    Category("nominal, SNR 100", _simple("nominal, SNR 100", 100.0)),
    Category("nominal, SNR 20", _simple("nominal, SNR 20", 20.0)),
    Category("nominal, SNR 5", _simple("nominal, SNR 5", 5.0)),
    Category("noiseless", _simple("noiseless", np.inf)),
    Category("two modes, ratio 2.2-2.4", _two("two modes, ratio 2.2-2.4", (2.2, 2.4), (0.2, 0.6), (1.0, 2.5), 50.0)),
    Category(
        "close modes, ratio 1.05-1.2", _two("close modes, ratio 1.05-1.2", (1.05, 1.2), (0.5, 1.0), (0.8, 1.2), 200.0)
    ),
    Category("heavy damping (1-3 visible cycles)", _heavy),
    Category("light damping", _simple("light damping", 20.0, g=(5.0, 50.0))),
    Category("zero damping", _simple("zero damping", 20.0, g=(0.0, 0.0))),
    Category("near Nyquist (0.40-0.48 fps)", _simple("near Nyquist (0.40-0.48 fps)", 20.0, f=(0.40 * FPS, 0.48 * FPS))),
    Category("0.8-1 cycle in the window", _cycles("0.8-1 cycle in the window", 0.8, 1.0, False)),
    Category("under 0.8 cycles", _cycles("under 0.8 cycles", 0.2, 0.8, True)),
    Category("pure noise", _noise),
    Category("constants", _constant),
    Category("12-30 samples", _simple("12-30 samples", 50.0, n=(12, 30), f=(2000.0, 8000.0), g=(100.0, 600.0))),
    Category("2,000 samples", _simple("2,000 samples", 20.0, n=2000, g=(20.0, 200.0))),
    Category(
        "huge offset (1e6 x amplitude)", _simple("huge offset (1e6 x amplitude)", 50.0, offset=1e6 * AMPLITUDE_MM)
    ),
    Category("linear drift (5x amplitude)", _simple("linear drift (5x amplitude)", 50.0, drift_per_window=5.0)),
    Category("spikes (20x amplitude)", _spikes),
    Category("runs of NaN", _nan_runs),
    Category("scale 1e-9", _simple("scale 1e-9", 50.0, scale=1e-9)),
    Category("scale 1e6", _simple("scale 1e6", 50.0, scale=1e6)),
]


def suite(per_category: int, seed: int = 0) -> list[Window]:
    """``per_category`` windows of every category, each category from its own seeded stream."""
    windows = []
    for k, category in enumerate(CATEGORIES):
        rng = np.random.default_rng([seed, k])
        windows += [category.draw(rng) for _ in range(per_category)]
    return windows


def cramer_rao_sd(window: Window) -> tuple[float, float]:
    """CRB standard deviations (Hz, 1/s) of the dominant mode's frequency and decay rate; NaN without noise."""
    if not window.modes or window.sigma == 0:
        return np.nan, np.nan
    n = np.flatnonzero(np.isfinite(window.values)).astype(np.float64)
    params = [window.offset, window.drift]
    for a, g, f, p in window.modes:  # a cos(w n + p) = (a cos p) cos w n + (-a sin p) sin w n
        params += [a * np.cos(p), -a * np.sin(p), 2 * np.pi * f / FPS, g / FPS]
    _, jac = kernels.columns(n, np.asarray(params))
    if window.drift == 0:
        jac = np.delete(jac, 1, axis=1)
    fisher = jac.T @ jac / window.sigma**2
    try:
        cov = np.linalg.inv(fisher)
    except np.linalg.LinAlgError:
        return np.nan, np.nan
    w_col = 4 if window.drift else 3
    sd = np.sqrt(np.abs(np.diag(cov)[[w_col, w_col + 1]]))
    return float(sd[0] * FPS / (2 * np.pi)), float(sd[1] * FPS)


def ours(values: np.ndarray, fps: float) -> list[Found]:
    """Our fit's modes, only when it judges the window ``ok``, with its interval half-widths."""
    r = fit_window(values, fps)
    if r.status != "ok":
        return []
    return [
        Found(
            m.frequency_hz,
            m.decay_rate_per_s,
            (
                (m.frequency_ci_hz[1] - m.frequency_ci_hz[0]) / 2,
                (m.decay_rate_ci_per_s[1] - m.decay_rate_ci_per_s[0]) / 2,
            )
            if m.frequency_ci_hz and m.decay_rate_ci_per_s
            else None,
        )
        for m in r.modes
    ]


def methods() -> dict[str, Callable[[np.ndarray, float], list[Found]]]:
    """Ours and its peers (harminv where installed)."""
    out = {"ours": ours, "curve_fit": curve_fit_found, "pencil": pencil_found}
    if available():
        out["harminv"] = harminv_found
    return out


def _nearest(found: list[Found], mode: tuple[float, float, float, float], within: float) -> Found | None:
    """The reported mode nearest the true one in frequency, when within ``within`` (relative) of it."""
    f = mode[2]
    best = min(found, key=lambda m: abs(m.frequency_hz - f), default=None)
    return best if best is not None and abs(best.frequency_hz - f) <= within * f else None


def _matches(found: list[Found], mode: tuple[float, float, float, float], length: int) -> bool:
    """Whether a reported mode is within the "ok" tolerances of the true one."""
    best = _nearest(found, mode, F_TOL)
    return best is not None and abs(best.decay_rate_per_s - mode[1]) <= G_TOL * max(mode[1], FPS / length)


@dataclass
class Score:
    """One method's answer on one window, scored."""

    ok: bool
    false_detection: bool
    seconds: float  # CPU time: this thread's and that of the processes it ran (harminv)
    error: tuple[float, float] = (np.nan, np.nan)  # dominant mode: |f error| Hz, |g error| 1/s (NaN: not found)
    covered: tuple[float, float] = (np.nan, np.nan)  # 1 / 0 when the interval holds the truth, NaN: no interval


def cpu_seconds() -> float:
    """CPU seconds of the calling thread and of the finished child processes (harminv runs as one): a method's cost,
    not the wall time, which the machine's other work inflates."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.thread_time() + children.ru_utime + children.ru_stime


def score(window: Window, method: Callable[[np.ndarray, float], list[Found]]) -> Score:
    """Run ``method`` on ``window`` and score it (module docstring)."""
    start = cpu_seconds()
    found = method(window.values, FPS)
    seconds = cpu_seconds() - start
    if not window.modes:
        return Score(not found, bool(found), seconds)
    matched = [_matches(found, m, window.values.size) for m in window.modes]
    ok = all(matched)
    if window.honest_only:
        ok = not found or matched[0]
    dominant = _nearest(found, window.modes[0], 0.05)  # errors are scored wherever the mode was found
    if dominant is None:
        return Score(ok, False, seconds)
    _, g, f, _ = window.modes[0]
    error = (abs(dominant.frequency_hz - f), abs(dominant.decay_rate_per_s - g))
    covered = (np.nan, np.nan)
    if dominant.half_width is not None:
        covered = tuple(float(e <= h) for e, h in zip(error, dominant.half_width))
    return Score(ok, False, seconds, error, covered)


@dataclass
class CategoryResult:
    """Scores of every method on one category's windows."""

    name: str
    windows: int
    exact: bool
    ok: dict[str, float] = field(default_factory=dict)  # share of windows ok
    false_detections: dict[str, int] = field(default_factory=dict)
    efficiency: dict[str, tuple[float, float]] = field(default_factory=dict)  # frequency, decay
    coverage: dict[str, tuple[float, float]] = field(default_factory=dict)
    ms_median: dict[str, float] = field(default_factory=dict)  # CPU per window
    ms_mean: dict[str, float] = field(default_factory=dict)
    ms_p99: dict[str, float] = field(default_factory=dict)


def run_suite(
    windows: list[Window], chosen: dict[str, Callable] | None = None, progress: bool = True
) -> tuple[list[CategoryResult], dict]:
    """Every method on every window: per-category results and the pooled efficiency and coverage (exact
    categories with noise) per method."""
    chosen = chosen or methods()
    ours(windows[0].values, FPS)  # warm-up: compilation and imports are not a window's cost
    crb = np.array([cramer_rao_sd(w) for w in windows])
    names = list(dict.fromkeys(w.category for w in windows))
    scores = {
        name: [score(w, m) for w in tqdm(windows, desc=name, unit="window", disable=not progress)]
        for name, m in chosen.items()
    }
    results, pooled = [], {}
    exact = np.array([w.exact and w.sigma > 0 and not w.honest_only for w in windows])
    for cat in names:
        rows = np.array([w.category == cat for w in windows])
        r = CategoryResult(cat, int(rows.sum()), bool(exact[rows].all()))
        for name, s in scores.items():
            picked = [x for x, keep in zip(s, rows) if keep]
            r.ok[name] = float(np.mean([x.ok for x in picked]))
            r.false_detections[name] = int(sum(x.false_detection for x in picked))
            r.ms_median[name], r.ms_mean[name], r.ms_p99[name] = _milliseconds(picked)
            if r.exact:
                r.efficiency[name] = _efficiency([x for x, keep in zip(s, rows) if keep], crb[rows])
                r.coverage[name] = _coverage(picked)
        results.append(r)
    for name, s in scores.items():
        picked = [x for x, keep in zip(s, exact) if keep]
        ms = _milliseconds(s)
        pooled[name] = {
            "efficiency": _efficiency(picked, crb[exact]),
            "coverage": _coverage(picked),
            "ok": float(np.mean([x.ok for x in s])),
            "ms_median": ms[0],
            "ms_mean": ms[1],
            "ms_p99": ms[2],
        }
    return results, pooled


def _milliseconds(scores: list[Score]) -> tuple[float, float, float]:
    """Median, mean and 99th percentile of the CPU time per window, ms."""
    ms = 1e3 * np.array([x.seconds for x in scores])
    return float(np.median(ms)), float(ms.mean()), float(np.percentile(ms, 99))


def _efficiency(scores: list[Score], crb: np.ndarray) -> tuple[float, float]:
    """median(|error| / CRB sd) / 0.674 for frequency and decay over the windows where the mode was found (within
    5 % in frequency: a tighter cut would leave out the large errors and flatter the median)."""
    errors = np.array([s.error for s in scores]).reshape(-1, 2)
    ratio = errors / crb
    return tuple(
        float(np.nanmedian(ratio[:, j]) / MEDIAN_ABS_NORMAL) if np.isfinite(ratio[:, j]).any() else np.nan
        for j in range(2)
    )


def _coverage(scores: list[Score]) -> tuple[float, float]:
    """Share of matched windows whose interval holds the truth, frequency and decay (NaN: no intervals)."""
    covered = np.array([s.covered for s in scores]).reshape(-1, 2)
    return tuple(float(np.nanmean(covered[:, j])) if np.isfinite(covered[:, j]).any() else np.nan for j in range(2))
