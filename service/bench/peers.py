"""The window fit's peers, for agreement tests and ``meniscope bench fit``: the same damped sinusoids found by other
methods. harminv (Mandelshtam & Taylor's filter diagonalisation, Debian package ``harminv``), scipy's ``curve_fit``
and a matrix pencil (Hua & Sarkar), each as its users would run it on a window."""

from __future__ import annotations

import shutil
import subprocess
import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import curve_fit

from service.analysis import pencil
from service.analysis.student import t_quantile
from service.errors import MeniscopeError


@dataclass(frozen=True)
class PeerMode:
    """One real damped mode ``A exp(-g t) cos(2 pi f t + phi)`` as harminv reports it (a +-f pair merged)."""

    frequency_hz: float
    decay_rate_per_s: float
    amplitude: float
    phase_rad: float
    error: float  # harminv's relative error estimate


@dataclass(frozen=True)
class Found:
    """A mode a method reports: frequency (Hz), decay rate (1/s) and, where the method gives them, the half-widths
    of their confidence intervals."""

    frequency_hz: float
    decay_rate_per_s: float
    half_width: tuple[float, float] | None = None


def available() -> bool:
    """Whether the ``harminv`` executable is on PATH."""
    return shutil.which("harminv") is not None


def harminv_modes(values: ArrayLike, fps: float, f_min: float = 0.0, f_max: float | None = None) -> list[PeerMode]:
    """Modes of ``values`` (N,) sampled at ``fps`` with |frequency| in [f_min, f_max] (default Nyquist), strongest first.

    The series is centred (its mean removed) first, and harminv searches from 0 Hz so that what is left of
    the offset gets a mode of its own near 0 Hz, which the ``f_min`` cut then drops. Its filters are
    widened (any Q >= 0.1; relative error <= 0.1, not relative to the best mode, which may be exact).
    """
    if not available():
        raise MeniscopeError("harminv", "not installed (Debian package harminv)")
    x = np.asarray(values, dtype=np.float64)
    text = "\n".join(f"{v:.17g}" for v in x - x.mean())
    f_max = fps / 2 if f_max is None else f_max
    done = subprocess.run(
        ["harminv", "-Q", "0.1", "-e", "1e300", "-E", "0.1", "-t", f"{1 / fps:.17g}", f"0-{f_max:.17g}"],
        input=text,
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise MeniscopeError(
            "harminv", f"failed: {done.stderr.strip().splitlines()[-1] if done.stderr.strip() else done.returncode}"
        )
    rows = [line.split(",") for line in done.stdout.splitlines()[1:] if line.strip()]
    table = np.array(rows, dtype=np.float64).reshape(-1, 6)  # frequency, decay, Q, amplitude, phase, error
    positive = table[(table[:, 0] >= max(f_min, 0.0)) & (table[:, 0] > 0) & (table[:, 0] <= f_max)]
    # a real mode is the pair +-f with half the amplitude each; harminv's e^(-i w t) makes the phase of +f -phi
    modes = [PeerMode(f, g, 2 * a, -phi, err) for f, g, _, a, phi, err in positive]
    return sorted(modes, key=lambda m: -m.amplitude)


def harminv_found(values: np.ndarray, fps: float) -> list[Found]:
    """harminv's modes (gaps filled linearly) turning at least 0.8 cycles over the window (slower ones stand for the offset)."""
    f_min = 0.8 * fps / values.size
    finite = np.isfinite(values)
    x = np.interp(np.arange(values.size), np.flatnonzero(finite), values[finite])  # harminv takes no gaps
    try:
        return [Found(m.frequency_hz, m.decay_rate_per_s) for m in harminv_modes(x, fps, f_min)]
    except (MeniscopeError, ValueError):  # its LAPACK refuses some series (a constant): it reports nothing
        return []


def pencil_found(values: np.ndarray, fps: float) -> list[Found]:
    """Hua & Sarkar's matrix pencil at its recommended size (N / 3 Hankel rows), six poles (two modes, the offset,
    one spare pair), the two most energetic pairs turning at least 0.8 cycles: a direct method with no refinement."""
    finite = np.isfinite(values)
    x = np.interp(np.arange(values.size), np.flatnonzero(finite), values[finite])
    x = x - np.median(x)
    w, g = pencil.damped_sinusoids(x, max(x.size // 3, 1), 6, 0.8)
    return [Found(wk * fps / (2 * np.pi), gk * fps) for wk, gk in zip(w[:2], g[:2])]


def _curve_model(t: np.ndarray, *p: float) -> np.ndarray:
    """c + v t + sum_k A_k exp(-g_k t) cos(w_k t + phi_k), t in samples."""
    y = p[0] + p[1] * t
    for a, g, w, phi in np.reshape(p[2:], (-1, 4)):
        y = y + a * np.exp(-g * t) * np.cos(w * t + phi)
    return y


def curve_fit_found(values: np.ndarray, fps: float, confidence: float = 0.95) -> list[Found]:
    """scipy's curve_fit as it is commonly used: offset, drift and one or two damped cosines started at the
    strongest peaks of the zero-padded periodogram (decay: one e-fold per window), the order chosen by BIC;
    intervals from its covariance (Student t)."""
    finite = np.isfinite(values)
    t, y = np.flatnonzero(finite).astype(float), values[finite]
    n = y.size
    if n < 8:
        return []
    centre, spread = np.median(y), max(np.ptp(y), 1e-300)
    y = (y - centre) / spread
    grid = np.interp(np.arange(values.size), t, y)
    grid = grid - np.polyval(np.polyfit(np.arange(grid.size), grid, 1), np.arange(grid.size))
    spectrum = np.abs(np.fft.rfft(grid, 8 * grid.size))
    freqs = np.fft.rfftfreq(8 * grid.size) * 2 * np.pi
    peaks = np.flatnonzero((spectrum[1:-1] > spectrum[:-2]) & (spectrum[1:-1] >= spectrum[2:])) + 1
    peaks = peaks[np.argsort(-spectrum[peaks])]
    best, best_bic = [], n * np.log(np.mean((y - np.polyval(np.polyfit(t, y, 1), t)) ** 2) + 1e-300) + 2 * np.log(n)
    for order in (1, 2):
        k = 2 + 4 * order
        if n <= k + 2 or peaks.size < order:
            break
        p0 = [0.0, 0.0]
        for w in freqs[peaks[:order]]:
            p0 += [np.ptp(grid) / 2, 1.0 / values.size, w, 0.0]
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                p, cov = curve_fit(_curve_model, t, y, p0=p0, maxfev=200 * (k + 1))
        except (RuntimeError, ValueError, np.linalg.LinAlgError):
            continue
        cost = float(np.sum((_curve_model(t, *p) - y) ** 2))
        bic = n * np.log(cost / n + 1e-300) + k * np.log(n)
        if bic < best_bic:
            half = t_quantile(n - k, confidence) * np.sqrt(np.abs(np.diag(cov)))
            modes = np.reshape(p[2:], (-1, 4))
            halves = np.reshape(half[2:], (-1, 4))
            best_bic, best = (
                bic,
                [
                    Found(abs(w) * fps / (2 * np.pi), g * fps, (hw * fps / (2 * np.pi), hg * fps))
                    for (_, g, w, _), (_, hg, hw, _) in zip(modes, halves)
                    if abs(w) * values.size / (2 * np.pi) >= 0.8
                ],
            )
    return best
