"""Window inversion by synthesis: the window's Eq. 1 motion refined on its frames through the renderer.

A per-frame inverse sees one frame at a time, and a frame of sparse highlights pins down only a few
combinations of (d, p, a, b); its estimates of a and b stay noisy and shrunk towards zero, which
biases the decay and amplitude of every window. Eq. 1 holds d and p still within a window and makes
a and b one damped mode each: ten numbers for the window's ~185 frames. This module finds them by
least squares on the pixels themselves,

    frame_t  ~  gain * blur_sigma(render(d, p, a(t), b(t))) + offset,

gain and offset solved exactly at each step (the exposure is not part of the contract) and the
camera's blur sigma fitted with the motion. Levenberg-Marquardt (``scipy.optimize.least_squares``)
starts from the per-frame method's estimate (d and p medians, one damped mode fitted to each of a(t)
and b(t)). Its Jacobian costs four renders of the window, not ten: the frames depend on the motion
only through each frame's (d, p, a, b), so d(frame)/d(coefficient) by finite differences, times
the exact d(coefficient)/d(parameter) of Eq. 1.

This is the accurate end of the speed/accuracy trade: seconds per window, where the fast path
needs milliseconds.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import binary_dilation, gaussian_filter
from scipy.optimize import least_squares
from threadpoolctl import ThreadpoolController

from service.analysis.fit import fit_window
from service.analysis.results import FitSettings, WindowResult
from service.physics import L1, L2, CoefficientRanges, WindowMotion
from service.render.renderer import Renderer

#: Search parameters: Eq. 1's window motion in WindowMotion's order (d, p, A1, g1, f1, phi1, A2, g2, f2,
#: phi2), then the camera's blur sigma (px), except that the search's g2 is mode 2's decay rate in excess of mode 1's
#: (:func:`_motion`): the membrane's mode 2 decays faster (scene.md's world, the simulator's ``g2_over_g1 > 1``), and
#: a search free to give it the slower decay reported it as the window's dominant mode (docs/benchmarks.md, "--refine:
#: mode 2 decays faster than mode 1"). Typical size of each parameter's change (mm, -, mm, 1/s, Hz, rad, ..., px): LM
#: works in units of these.
_SCALE = np.array([1e-3, 1e-2, 1e-3, 30.0, 5.0, 0.05, 1e-3, 60.0, 10.0, 0.1, 0.1])
#: Finite-difference steps of the per-frame coefficients (d mm, p, a mm, b mm) and of the blur (px):
#: large enough to move a highlight across the supersampled pixel grid, small against the motion.
_COEFFICIENT_STEP = np.array([1e-3, 1e-2, 1e-3, 1e-3])
_BLUR_STEP = 0.05
#: Start of the camera's blur (px): the "lab" camera preset's focus.
_START_BLUR = 0.7
#: The largest blur sigma (px) the search renders: beyond it a window's frames are a smear, no camera's focus. LM's
#: steps are unbounded, and one to sigma 5e9 px asked scipy's Gaussian for a 161 GiB kernel (a Blender Cycles window
#: of the calibrated near-mirror scene, docs/new_camera.md).
_MAX_BLUR = 10.0
#: Amplitude factors of the starts tried (the one whose frames fit best is refined): the shipped models'
#: a(t) has a slope of 0.2-0.6 against the truth on unseen recordings.
_AMPLIFY = (1.0, 2.0, 4.0)
#: Shifts of the sag p of the starts tried (the shipped models' per-frame p is off by ~0.03-0.08 RMS).
_SHIFT_P = (-0.03, 0.0, 0.03)
#: Sags tried before them, across :class:`CoefficientRanges`' p, d moved to keep the centre's offset d + p R: from a
#: per-frame p of the wrong sign LM let both modes die within a frame to move the surface's still shape instead
#: (docs/benchmarks.md, "--refine: mode 2 decays faster than mode 1").
_SAGS = 13
#: l2 / l1 of scene.md: mode 2's frequency over mode 1's for an ideal membrane.
_BESSEL_RATIO = L2 / L1
#: Mode 2's frequency over mode 1's where the frames' spectrum is searched for mode 2: the membrane's
#: l2 / l1 = 2.30 give or take the 2.2-2.4 a real meniscus departs from it, with a margin.
_MODE_2_RATIO = (2.1, 2.5)
#: Zero padding of the frames' spectrum (times the window's frames): peaks read to a few Hz, not 100.
_PAD = 16
#: Mode 1 (amplitude mm, decay 1/s, frequency Hz, phase) where neither a(t) nor b(t) shows a resolved mode.
_TYPICAL_MODE_1 = (0.015, 500.0, 1500.0, 0.0)
#: Frames a window needs for the search (ten parameters and the blur, with room to spare).
MIN_FRAMES = 24
#: A pixel moves with the window where its value's spread over the window exceeds this many times the frames'
#: median spread (the noise's, where most pixels are still), ...
_MOVING = 3.0
#: ... or lies within this many pixels of one that does.
_REACH = 3
#: LM stops where a step changes the search's point by less than this (relative) or the cost by less than _FTOL:
#: tighter, it ran to its last evaluation (its Jacobian, by finite differences of blurred renders, is rough at those
#: scales) for the same motion (docs/benchmarks.md).
_XTOL = 1e-4
_FTOL = 1e-5
#: Evaluations LM may spend per window (each one render of the window, each Jacobian four more).
_EVALUATIONS = 100
#: Directions over the sun's disc in the search's renders (the renderer's default is 4). Cycles, a real camera, sees
#: the whole disc; at 4 directions a near-mirror's highlight is four small ones, and even at the default scene's
#: roughness the true motion's frames fit worse than at 16, beyond which more directions change nothing the noise
#: does not (docs/new_camera.md). The renders cost a fifth to a half more.
SUN_SAMPLES = 16
#: The search runs its BLAS on one thread wherever it runs: a BLAS on several threads sums a long dot product (the
#: gain and offset of each evaluation, the pixel fit's J'J) in per-thread pieces, so its last bits, the search's
#: path and the REPORT depended on the threads of the process (a forked pool's one per core, Dask's workers one).
_BLAS = ThreadpoolController()
#: Side (px) of the image tiles whose pixels are one cluster of the pixel fit's covariance (:func:`covariance`).
TILE = 12
#: A parameter takes part in a direction the pixel fit does not pin down where its weight in it exceeds this.
_NULL = 1e-6


@dataclass(frozen=True)
class Refined:
    """A window's motion refined on its frames, and how the search went."""

    motion: WindowMotion
    blur_sigma_px: float
    rms_start: float  # pixel residual RMS at the start over the moving pixels, in stored pixel units
    rms: float  # and at the end
    evaluations: int  # renders of the window the search made


def start_motion(coefficients: np.ndarray, t: np.ndarray, fps: float) -> WindowMotion:
    """The search's start from a window's per-frame estimates (m, 4) at consecutive times ``t`` (s since the
    window start): d and p medians, one damped mode fitted to a(t) and one to b(t) (Eq. 1 puts mode 1 in a
    and mode 2 in b). A coefficient without a resolved mode (``ok``) starts from the other's: mode 2 at the
    membrane's frequency ratio l2 / l1 above mode 1 (and below it for mode 1), decaying twice as fast."""
    d, p = np.nanmedian(coefficients[:, 0]), np.nanmedian(coefficients[:, 1])
    t0 = float(t[0])  # the fits count time from t0: back to the window start
    found = []
    for column in (2, 3):
        result = fit_window(coefficients[:, column], fps, FitSettings(max_modes=1))
        m = result.modes[0] if result.status == "ok" else None
        found.append(
            None
            if m is None
            else (
                m.amplitude_mm * np.exp(m.decay_rate_per_s * t0),
                m.decay_rate_per_s,
                m.frequency_hz,
                m.phase_rad - 2 * np.pi * m.frequency_hz * t0,
            )
        )
    one, two = found
    if one is None and two is None:
        one = _TYPICAL_MODE_1
    if one is None:
        one = (2.5 * two[0], 0.5 * two[1], two[2] / _BESSEL_RATIO, 0.0)
    return _canonical(np.array([d, p, *one, *(two or _mode_2_of(one))], np.float64))


def _mode_2_of(one: tuple[float, ...]) -> tuple[float, ...]:
    """Mode 2 (amplitude, decay, frequency, phase) where only mode 1 is known: at the membrane's frequency ratio
    l2 / l1 above it, decaying twice as fast, 0.4 of its amplitude."""
    return (0.4 * one[0], 2.0 * one[1], one[2] * _BESSEL_RATIO, 0.0)


def window_start(result: WindowResult, coefficients: np.ndarray, radius_mm: float) -> WindowMotion | None:
    """The search's start from a window's fit (its modes, t from the window start, by frequency: mode 1 the lower;
    mode 2 as :func:`_mode_2_of` where the fit found only one) and the per-frame estimates' median sag p, its rim d
    the fitted offset d + p R less p R; None where the fit found no mode. With the window model the fit's amplitude
    and offset are not shrunk as the per-frame a(t) and b(t) are: no amplified variants are needed from it."""
    if not result.modes or result.offset_mm is None:
        return None
    modes = [
        (m.amplitude_mm, m.decay_rate_per_s, m.frequency_hz, m.phase_rad)
        for m in sorted(result.modes, key=lambda m: m.frequency_hz)
    ]
    p = float(np.nanmedian(coefficients[:, 1]))
    two = modes[1] if len(modes) > 1 else _mode_2_of(modes[0])
    return _canonical(np.array([result.offset_mm - p * radius_mm, p, *modes[0], *two], np.float64))


def frames_start(start: WindowMotion, frames: np.ndarray, t: np.ndarray) -> WindowMotion:
    """``start`` with each mode's frequency, phase and decay read from the window's frames (m, H, W) at
    consecutive times ``t``, not from the per-frame method, whose a(t) and b(t) can miss a mode (a slow swing
    or the other mode taken for it) where every pixel still oscillates with it. Mode 1 is the strongest peak of
    the pixels' summed power spectrum (two cycles per window up to Nyquist), mode 2 the strongest within
    :data:`_MODE_2_RATIO` of it (the Bessel ratio where none is). Each mode's amplitude keeps the RMS the start
    gives it over the window (the per-frame method sees how much a(t) and b(t) move, if not when), kept
    within a tenth of and the whole of its coefficient's :class:`CoefficientRanges`."""
    y = frames.reshape(len(t), -1).astype(np.float64)
    y -= y.mean(axis=0)
    dt = float(np.median(np.diff(t)))
    n = _PAD * len(t)
    freqs = np.fft.rfftfreq(n, dt)
    power = (np.abs(np.fft.rfft(y * np.hanning(len(t))[:, None], n, axis=0)) ** 2).sum(axis=1)
    f1 = _peak(freqs, power, 2.0 / (len(t) * dt), freqs[-1]) or start.f1
    f2 = _peak(freqs, power, _MODE_2_RATIO[0] * f1, min(_MODE_2_RATIO[1] * f1, freqs[-1])) or f1 * _BESSEL_RATIO
    ranges = CoefficientRanges()
    modes = []
    for amplitude, decay, frequency, phase, most in (
        (start.A1, start.g1, f1, start.phi1, ranges.a[1]),
        (start.A2, start.g2, f2, start.phi2, ranges.b[1]),
    ):
        new_decay, new_phase = _decay_and_phase(y, t, frequency, phase)
        rms = np.sqrt(np.mean(np.exp(-2 * decay * t)) / np.mean(np.exp(-2 * new_decay * t)))
        modes += [np.clip(amplitude * rms, 0.1 * most, most), new_decay, frequency, new_phase]
    return WindowMotion(start.d, start.p, *map(float, modes))


def _peak(freqs: np.ndarray, power: np.ndarray, low: float, high: float) -> float | None:
    """The frequency of the strongest local maximum of ``power`` in [low, high], None where there is none."""
    inner = (power[1:-1] > power[:-2]) & (power[1:-1] >= power[2:]) & (freqs[1:-1] >= low) & (freqs[1:-1] <= high)
    found = np.flatnonzero(inner) + 1
    return float(freqs[found[np.argmax(power[found])]]) if found.size else None


def _decay_and_phase(y: np.ndarray, t: np.ndarray, frequency: float, near: float) -> tuple[float, float]:
    """A mode's decay rate and phase at ``frequency`` from the centred pixel series ``y`` (m, pixels). Each pixel
    follows the mode times its own sensitivity s: its projection on exp(-2 pi i f t) is s A e^(i phi) / 2, so
    the sum of the projections squared has angle 2 phi (phi up to pi: the one nearer ``near`` is taken), and
    the ratio of that sum's magnitudes over the window's two halves is exp(2 g half-length)."""
    rotated = y * np.exp(-2j * np.pi * frequency * t)[:, None]
    half = len(t) // 2
    first, second = (np.abs(np.sum(rotated[part].sum(axis=0) ** 2)) for part in (slice(0, half), slice(half, 2 * half)))
    decay = max(0.0, float(np.log(first / second) / (2 * (t[half] - t[0])))) if second > 0 else 0.0
    phase = float(np.angle(np.sum(rotated.sum(axis=0) ** 2)) / 2)
    if np.cos(phase - near) < 0:
        phase += np.pi
    return decay, float(np.mod(phase, 2 * np.pi))


def moving_pixels(frames: np.ndarray) -> np.ndarray:
    """The pixels (H, W) bool of a window's frames (m, H, W) that its motion can move: those whose value varies
    over the window by more than :data:`_MOVING` times the frames' typical (median) temporal spread, and within
    :data:`_REACH` px of them (a highlight moves between frames, and a rendered one off by a few pixels must still
    be seen). Every pixel where none varies (a settled window). The rest are the static nozzle and the dark bore:
    their residuals do not depend on the motion, yet carried most of the search's arithmetic (docs/benchmarks.md)."""
    spread = frames.std(axis=0)
    moving = spread > _MOVING * np.median(spread)
    if not moving.any():
        return np.ones(spread.shape, bool)
    return binary_dilation(moving, iterations=_REACH)


class _Problem:
    """Residuals and Jacobian of one window's frames at its :func:`moving_pixels`, in search units
    x = parameters / _SCALE."""

    def __init__(self, renderer: Renderer, frames: np.ndarray, t: np.ndarray) -> None:
        self.renderer, self.t = renderer, t
        frames = frames.astype(np.float64)
        self.pixels = moving_pixels(frames).ravel()
        self.y = frames.reshape(len(t), -1)[:, self.pixels]
        self.renders, self._key = 0, b""

    def _render(self, coefficients: np.ndarray) -> np.ndarray:
        """Linear renders (k m, H, W) of stacked per-frame coefficients (k m, 4)."""
        self.renders += len(coefficients) // len(self.t)
        return self.renderer.render(coefficients)

    def _seen(self, frames: np.ndarray) -> np.ndarray:
        """Frames (..., m, H, W) at the problem's pixels: (..., m, P)."""
        return frames.reshape(*frames.shape[:-2], -1)[..., self.pixels]

    def cost(self, motion: WindowMotion, blur: float) -> float:
        """Mean squared residual of ``motion`` seen through ``blur`` (px): one render."""
        return float(np.mean(self.residuals(_point(motion, blur)) ** 2))

    def best(self, motions: list[WindowMotion]) -> tuple[float, WindowMotion]:
        """The cost and the motion of whichever of ``motions`` fits the frames best at the start's blur."""
        costs = [self.cost(m, _START_BLUR) for m in motions]
        return min(costs), motions[int(np.argmin(costs))]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Frames minus gain * blurred render + offset, gain and offset the least-squares ones; (m H W,)."""
        params = x * _SCALE
        coefficients = _coefficients(params, self.t)
        if not (np.all(np.isfinite(coefficients)) and abs(params[10]) <= _MAX_BLUR):
            # a step to absurd amplitudes or blur: as bad as a black window, not a crash
            return np.abs(self.y).ravel() + np.abs(self.y).max()
        self._sharp = self._render(coefficients)
        model = self._seen(gaussian_filter(self._sharp, (0, abs(params[10]), abs(params[10]))))
        design = np.stack([model.ravel(), np.ones(model.size)], axis=1)
        self._gain, offset = np.linalg.lstsq(design, self.y.ravel(), rcond=None)[0]
        self._model, self._key = model, x.tobytes()
        return (self._gain * model + offset - self.y).ravel()

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """d residuals / d x, shape (m H W, 11): four renders with one coefficient stepped, chained with Eq. 1."""
        if x.tobytes() != self._key:
            self.residuals(x)
        params, m = x * _SCALE, len(self.t)
        sigma = abs(params[10])
        base = _coefficients(params, self.t)
        stepped = np.concatenate([base + np.eye(4)[j] * _COEFFICIENT_STEP[j] for j in range(4)])
        models = gaussian_filter(self._render(stepped).reshape(4, m, *self.renderer.shape), (0, 0, sigma, sigma))
        per_coefficient = (self._seen(models) - self._model) * (self._gain / _COEFFICIENT_STEP[:, None, None])
        chain = _coefficient_derivatives(params, self.t)  # (m, 10, 4)
        motion = np.einsum("jmp,mkj->mpk", per_coefficient, chain).reshape(-1, 10)
        blurred = self._seen(gaussian_filter(self._sharp, (0, sigma + _BLUR_STEP, sigma + _BLUR_STEP)))
        blur = (self._gain * (blurred - self._model) / _BLUR_STEP).reshape(-1, 1)
        return np.hstack([motion, blur]) * _SCALE


def _coefficients(params: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Per-frame (d, p, a, b), shape (m, 4), of the search's parameters ``params[:10]`` (:func:`_motion`) at ``t``
    (s)."""
    return WindowMotion(*_motion(params)).coefficients(t).to_array()


def _coefficient_derivatives(params: np.ndarray, t: np.ndarray) -> np.ndarray:
    """d(d, p, a, b)(t) / d(search parameters, :func:`_motion`): shape (m, 10, 4), exact (mode 2's decay moves
    with mode 1's parameter too)."""
    out = np.zeros((t.size, 10, 4))
    out[:, 0, 0] = out[:, 1, 1] = 1.0
    motion = _motion(params)
    for first, column, decay in ((2, 2, motion[3]), (6, 3, motion[7])):
        amplitude, _, frequency, phase = params[first : first + 4]
        envelope = np.exp(-decay * t)
        angle = 2 * np.pi * frequency * t + phase
        cos, sin = envelope * np.cos(angle), envelope * np.sin(angle)
        out[:, first, column] = cos
        out[:, first + 1, column] = -t * amplitude * cos * _sign(params[first + 1])
        out[:, first + 2, column] = -2 * np.pi * t * amplitude * sin
        out[:, first + 3, column] = -amplitude * sin
    out[:, 3, 3] = out[:, 7, 3] * _sign(params[7]) * _sign(params[3])  # d b / d g2 times d g2 / d (mode 1's decay)
    return out


def _canonical(params: np.ndarray) -> WindowMotion:
    """Positive amplitudes, decays and frequencies (a sign moves into the phase), phases in [0, 2 pi)."""
    p = params[:10].copy()
    for first in (2, 6):
        amplitude, decay, frequency, phase = p[first : first + 4]
        decay = abs(decay)
        if frequency < 0:
            frequency, phase = -frequency, -phase
        if amplitude < 0:
            amplitude, phase = -amplitude, phase + np.pi
        p[first : first + 4] = amplitude, decay, frequency, np.mod(phase, 2 * np.pi)
    return WindowMotion(*map(float, p))


def _along_sag(problem: _Problem, motion: WindowMotion) -> WindowMotion:
    """``motion`` or, where one fits the frames better, the same motion at one of :data:`_SAGS` sags across the
    coefficient ranges with the same offset of the centre (d + p R): the window fit pins the centre's offset, not
    how it splits between the rim d and the sag p, which the per-frame p can get far wrong."""
    radius = problem.renderer.scene.nozzle.radius_mm
    offset = motion.d + motion.p * radius
    sags = np.linspace(*CoefficientRanges().p, _SAGS)
    return problem.best([motion] + [replace(motion, p=float(p), d=float(offset - p * radius)) for p in sags])[1]


def _variants(start: WindowMotion, amplify: tuple[float, ...] = _AMPLIFY) -> list[WindowMotion]:
    """``start`` with both mode amplitudes times each of ``amplify``, mode 1 as it is and turned over
    (phase + pi), p moved by each of :data:`_SHIFT_P`: per-frame estimates of a and b shrink towards 0 (a
    regressor given an ambiguous image returns the mean of its possible shapes), a bulge and a dip of the
    same size can look alike from below, and the sag p trades against mode 1 near the centre (both curve it)."""
    return [
        replace(start, p=start.p + sag, A1=start.A1 * k, A2=start.A2 * k, phi1=start.phi1 + turn)
        for k in amplify
        for turn in (0.0, np.pi)
        for sag in _SHIFT_P
    ]


def within_ranges(motion: WindowMotion, t: np.ndarray) -> bool:
    """Whether a window's per-frame (d, p, a, b) at times ``t`` lie inside the default :class:`CoefficientRanges`
    (where renders are informative and the models are trained; a search that leaves them has fitted the frames'
    noise with a motion no meniscus makes)."""
    ranges = CoefficientRanges()
    low, high = np.array([ranges.d, ranges.p, ranges.a, ranges.b]).T
    coefficients = motion.coefficients(t).to_array()
    return bool(np.all((coefficients >= low) & (coefficients <= high)))


def plausible(motion: WindowMotion, t: np.ndarray) -> bool:
    """Whether a window's motion is one the analysis can report: mode 1 at two cycles per window or more (a
    slower swing is not an oscillation the window can show), below mode 2, below the Nyquist frequency of the
    times ``t`` (consecutive frames), and :func:`within_ranges`."""
    dt = float(np.median(np.diff(t)))
    return bool(2.0 / (len(t) * dt) <= motion.f1 < motion.f2 < 0.5 / dt and within_ranges(motion, t))


def _point(motion: WindowMotion, blur: float) -> np.ndarray:
    """The search's point (its units: :data:`_SCALE`) of a motion and blur (px); a motion whose mode 2 decays slower
    than mode 1 starts from both at mode 1's rate."""
    params = np.array([*motion.as_dict().values(), blur])
    params[7] = max(params[7] - params[3], 0.0)
    return params / _SCALE


def _motion(params: np.ndarray) -> np.ndarray:
    """The motion (10,) in WindowMotion's order of the search's parameters (:data:`_SCALE`'s order, not scaled):
    decay parameters stand for their absolute values (a decay rate is >= 0 without bounds on the search), g2 for
    mode 1's decay plus its own."""
    p = np.array(params[:10], np.float64)
    p[3] = abs(p[3])
    p[7] = p[3] + abs(p[7])
    return p


def _sign(x: float) -> float:
    """d|x| / dx, taken as 1 at 0 (one side of the kink: a decay parameter at 0 still moves the frames)."""
    return -1.0 if x < 0 else 1.0


def _mirrored(motion: WindowMotion) -> WindowMotion:
    """The motion's surface mirrored about its rim plane (p and both modes of the other sign), which can look
    alike from below: on a window of s101_lab the search from the network's start ended at p = -0.125, mode 1
    turned over, where the truth was p = +0.126, with 11 times the truth's pixel residual (two more windows
    ended at p of the wrong sign, +0.109 for -0.111 and +0.098 for -0.099, d off by 0.02-0.03 mm)."""
    return replace(motion, p=-motion.p, phi1=motion.phi1 + np.pi, phi2=motion.phi2 + np.pi)


def _search(problem: _Problem, motion: WindowMotion, blur: float) -> tuple[WindowMotion, float, float]:
    """LM from ``motion`` and ``blur``, then once more from the mirror of where it ended (:func:`_mirrored`;
    LM, not the mirror's own residual, decides: the mirrored minimum's rim d sits elsewhere, by 0.023 and
    0.027 mm on two windows of s101_lab): the motion, blur and mean squared residual of the better end."""
    first = _levenberg_marquardt(problem, motion, blur)
    return min(first, _levenberg_marquardt(problem, _mirrored(first[0]), first[1]), key=lambda end: end[2])


def _levenberg_marquardt(problem: _Problem, motion: WindowMotion, blur: float) -> tuple[WindowMotion, float, float]:
    """LM from ``motion`` and ``blur``: the motion, blur and mean squared residual it ends at."""
    found = least_squares(
        problem.residuals,
        _point(motion, blur),
        jac=problem.jacobian,
        method="lm",
        xtol=_XTOL,
        ftol=_FTOL,
        max_nfev=_EVALUATIONS,
    )
    params = found.x * _SCALE
    return _canonical(_motion(params)), abs(float(params[10])), float(np.mean(found.fun**2))


@_BLAS.wrap(limits=1, user_api="blas")
def refine_window(
    renderer: Renderer, frames: np.ndarray, t: np.ndarray, start: WindowMotion, fitted: WindowMotion | None = None
) -> Refined:
    """Refine ``start`` on a window's ROI frames (m, H, W) at times ``t`` (m,) s since the window start. Two
    starts: ``start`` (or the window fit's ``fitted``, :func:`window_start`, where given: its amplitudes as they
    are) and :func:`frames_start` of it; each one moved to its best sag (:func:`_along_sag`), its :func:`_variants`
    rendered once, and :func:`_search` runs from the best-fitting variant of the better start, then (where it ends
    in an implausible motion, see :func:`plausible`) from the other's. The plausible result is returned, else the
    one that fits best."""
    t = np.asarray(t, np.float64)
    problem = _Problem(renderer, frames, t)
    base, amplify = (start, _AMPLIFY) if fitted is None else (fitted, (1.0,))
    starts = sorted(
        (
            problem.best(_variants(_along_sag(problem, motion), amplify))
            for motion in (base, frames_start(base, frames, t))
        ),
        key=lambda pair: pair[0],
    )
    ends = []
    for cost, motion in starts:
        ends.append((*_search(problem, motion, _START_BLUR), cost))
        if plausible(ends[-1][0], t):
            break
    motion, blur, cost, start_cost = next(
        (end for end in reversed(ends) if plausible(end[0], t)), min(ends, key=lambda end: end[2])
    )
    return Refined(motion, blur, float(np.sqrt(start_cost)), float(np.sqrt(cost)), problem.renders)


@_BLAS.wrap(limits=1, user_api="blas")
def polish(renderer: Renderer, frames: np.ndarray, t: np.ndarray, motion: WindowMotion, blur: float) -> Refined:
    """LM alone from a ``motion`` and ``blur`` (px) already near the window's (the same window refined through a
    scene close to ``renderer``'s): no starts tried, no mirror. One render more than the search, for its start's RMS."""
    problem = _Problem(renderer, frames, np.asarray(t, np.float64))
    start_cost = problem.cost(motion, blur)
    end, end_blur, cost = _levenberg_marquardt(problem, motion, blur)
    return Refined(end, end_blur, float(np.sqrt(start_cost)), float(np.sqrt(cost)), problem.renders)


@_BLAS.wrap(limits=1, user_api="blas")
def covariance(renderer: Renderer, frames: np.ndarray, t: np.ndarray, refined: Refined) -> tuple[np.ndarray, int]:
    """Covariance (11, 11) of a refined window's motion (WindowMotion's order, d ... phi2) and blur (px) from its
    pixel fit at the optimum, and the number of clusters it was estimated from: :func:`cluster_covariance` with
    each :data:`TILE` x :data:`TILE` px image tile (all frames) one cluster. The error that matters is the
    renderer's mismatch with the camera, correlated across a highlight and over the window's frames, not the pixels'
    noise, which s^2 (J'J)^-1 assumes independent (docs/benchmarks.md, "Intervals of the refined windows"). Five
    renders."""
    problem = _Problem(renderer, frames, np.asarray(t, np.float64))
    x = _point(refined.motion, refined.blur_sigma_px)
    residuals, jac = problem.residuals(x), problem.jacobian(x)
    clusters = np.tile(tile_clusters(problem.pixels, renderer.shape), len(t))
    searched = cluster_covariance(jac, residuals, clusters) * np.outer(_SCALE, _SCALE)
    return _motion_covariance(searched), int(clusters.max()) + 1


def _motion_covariance(searched: np.ndarray) -> np.ndarray:
    """The covariance (11, 11) of the motion and blur from that of the search's parameters at a point of
    :func:`_point` (decays >= 0: g2 = g1 + excess), by sums alone (an entry may be infinite, and inf * 0 is NaN)."""
    out = searched.copy()
    out[7, :] += searched[3, :]
    out[:, 7] += out[:, 3]
    return out


def tile_clusters(pixels: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The tile (0 ... G - 1, numbered among the tiles that hold any) of each selected pixel of an image of
    ``shape``, ``pixels`` (H W,) bool selecting them: square tiles of :data:`TILE` px from the top left corner."""
    rows, columns = np.divmod(np.flatnonzero(pixels), shape[1])
    tile = (rows // TILE) * -(-shape[1] // TILE) + columns // TILE
    return np.unique(tile, return_inverse=True)[1].ravel()


def cluster_covariance(jacobian: np.ndarray, residuals: np.ndarray, clusters: np.ndarray) -> np.ndarray:
    """The cluster-robust (sandwich) covariance of a least-squares fit at its optimum, (k, k) for a ``jacobian``
    (n, k) of the ``residuals`` (n,), observations in ``clusters`` (n,) labelled 0 ... G - 1: H^-1 (sum_c s_c
    s_c') H^-1 G / (G - 1), H = J'J, s_c = J_c' r_c. Errors correlated within a cluster, independent between
    clusters, of any variance: s^2 H^-1 holds only for independent ones. Infinite for the parameters of a direction
    the observations do not pin down (H singular: a mode that has died out before the window's first frame), the
    others' from the fit without them; everywhere where G < 2 (no spread between clusters to measure)."""
    k = jacobian.shape[1]
    count = int(clusters.max()) + 1 if clusters.size else 0
    out = np.full((k, k), np.inf)
    normal = jacobian.T @ jacobian
    values, vectors = np.linalg.eigh(normal)
    null = vectors[:, values <= max(values.max(), 0.0) * k * np.finfo(np.float64).eps]
    kept = ~np.any(np.abs(null) > _NULL, axis=1)
    if count < 2 or not kept.any():
        return out
    weighted = jacobian[:, kept] * residuals[:, None]
    scores = np.stack([np.bincount(clusters, column, count) for column in weighted.T], axis=1)
    bread = np.linalg.inv(normal[np.ix_(kept, kept)])
    out[np.ix_(kept, kept)] = bread @ (scores.T @ scores) @ bread * count / (count - 1)
    return out
