"""harminv (Mandelshtam & Taylor's filter diagonalisation, Debian package ``harminv``) as an independent peer
of the window fit: the same damped sinusoids found by another method, for agreement tests and benchmarks."""
from __future__ import annotations

import shutil
import subprocess
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from service.errors import MeniscopeError


@dataclass(frozen=True)
class PeerMode:
    """One real damped mode ``A exp(-g t) cos(2 pi f t + phi)`` as harminv reports it (a +-f pair merged)."""

    frequency_hz: float
    decay_rate_per_s: float
    amplitude: float
    phase_rad: float
    error: float  # harminv's relative error estimate


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
    done = subprocess.run(["harminv", "-Q", "0.1", "-e", "1e300", "-E", "0.1", "-t", f"{1 / fps:.17g}", f"0-{f_max:.17g}"], input=text,
                          capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise MeniscopeError("harminv", f"failed: {done.stderr.strip().splitlines()[-1] if done.stderr.strip() else done.returncode}")
    rows = [line.split(",") for line in done.stdout.splitlines()[1:] if line.strip()]
    table = np.array(rows, dtype=np.float64).reshape(-1, 6)  # frequency, decay, Q, amplitude, phase, error
    positive = table[(table[:, 0] >= max(f_min, 0.0)) & (table[:, 0] > 0) & (table[:, 0] <= f_max)]
    # a real mode is the pair +-f with half the amplitude each; harminv's e^(-i w t) makes the phase of +f -phi
    modes = [PeerMode(f, g, 2 * a, -phi, err) for f, g, _, a, phi, err in positive]
    return sorted(modes, key=lambda m: -m.amplitude)
