"""The physics prior: Eq. 1 of Price et al. (2022), a damped circular membrane.

    D(r, t) = d + p (R - r^2 / R) + a(t) J0(l1 r / R) + b(t) J0(l2 r / R)      (Eq. 1)
    a(t) = A1 exp(-g1 t) cos(2 pi f1 t + phi1),   b(t) likewise with mode 2

``D`` is the downward displacement of the metal surface in mm (``z = -D``), ``r`` the
radius in mm (0 <= r <= R), ``d`` mm, ``p`` dimensionless, ``a``, ``b`` mm, ``t`` s from
the start of the window, ``g`` 1/s, ``f`` Hz. Every function broadcasts over any batch
shape (radii x frames x parameter sets) and returns float64 without NaN for finite input.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import j0, j1

from service.errors import MeniscopeError

#: First two positive roots of J0: the Bessel modes vanish at the rim r = R.
L1 = 2.404825557695773
L2 = 5.520078110286311


def _radius(r: ArrayLike, R: float) -> np.ndarray:
    """Radii as float64, clipped to the bore [0, R] where Eq. 1 is defined."""
    return np.clip(np.asarray(r, dtype=np.float64), 0.0, R)


def displacement(r: ArrayLike, d: ArrayLike, p: ArrayLike, a: ArrayLike, b: ArrayLike, R: float) -> np.ndarray:
    """Downward displacement D(r) in mm (Eq. 1); all arguments broadcast together."""
    r = _radius(r, R)
    return d + p * (R - r * r / R) + a * j0(L1 * r / R) + b * j0(L2 * r / R)


def slope(r: ArrayLike, p: ArrayLike, a: ArrayLike, b: ArrayLike, R: float) -> np.ndarray:
    """Radial slope dD/dr (dimensionless), analytic: d/dx J0(x) = -J1(x); zero at r = 0."""
    r = _radius(r, R)
    return -2.0 * p * r / R - a * (L1 / R) * j1(L1 * r / R) - b * (L2 / R) * j1(L2 * r / R)


def centre_displacement(d: ArrayLike, p: ArrayLike, a: ArrayLike, b: ArrayLike, R: float) -> np.ndarray:
    """D(0, t) = d + p R + a + b (mm): the quantity the window analysis follows."""
    return np.asarray(d, dtype=np.float64) + np.asarray(p) * R + np.asarray(a) + np.asarray(b)


def damped_mode(
    t: ArrayLike, amplitude: ArrayLike, decay: ArrayLike, frequency: ArrayLike, phase: ArrayLike
) -> np.ndarray:
    """A exp(-g t) cos(2 pi f t + phi); the envelope underflows cleanly to 0 for large g t.

    ``decay`` must be >= 0 and ``t`` >= 0 (time since the window start): the envelope
    is then in [0, 1] and no overflow is possible.
    """
    t = np.asarray(t, dtype=np.float64)
    with np.errstate(under="ignore"):
        envelope = np.exp(-np.asarray(decay, dtype=np.float64) * t)
    return amplitude * envelope * np.cos(2.0 * np.pi * np.asarray(frequency) * t + phase)


def coefficient_array(coeffs: ArrayLike, where: str = "coefficients") -> np.ndarray:
    """Coefficients as float64 of shape (N, 4) (columns d, p, a, b), or a MeniscopeError saying what is wrong."""
    arr = np.asarray(coeffs, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == 4:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise MeniscopeError(where, f"expected shape (N, 4) with columns d, p, a, b, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise MeniscopeError(where, "contain NaN or infinite values")
    return arr


@dataclass(frozen=True)
class Coefficients:
    """Per-frame shape coefficients of Eq. 1, each an array of shape (N,)."""

    d: np.ndarray
    p: np.ndarray
    a: np.ndarray
    b: np.ndarray

    @classmethod
    def from_array(cls, array: ArrayLike) -> Coefficients:
        """From an array of shape (N, 4) with columns d, p, a, b."""
        arr = np.asarray(array, dtype=np.float64).reshape(-1, 4)
        return cls(*(arr[:, i].copy() for i in range(4)))

    def to_array(self) -> np.ndarray:
        """Shape (N, 4), columns d, p, a, b."""
        return np.stack([self.d, self.p, self.a, self.b], axis=1)

    def centre(self, R: float) -> np.ndarray:
        """Centre displacement D(0, t) per frame (mm)."""
        return centre_displacement(self.d, self.p, self.a, self.b, R)

    def __len__(self) -> int:
        return int(np.asarray(self.d).shape[0])


@dataclass(frozen=True)
class WindowMotion:
    """The motion of one window between ejections (Eq. 1's ten parameters): the truth of a simulated recording
    (scene.md, "Recordings and ground truth") or an estimate of it (refinement by synthesis)."""

    d: float
    p: float
    A1: float
    g1: float
    f1: float
    phi1: float
    A2: float
    g2: float
    f2: float
    phi2: float

    def coefficients(self, t: ArrayLike) -> Coefficients:
        """Coefficients at times ``t`` (s since the window start), shape (N,) each."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        return Coefficients(
            d=np.full(t.shape, self.d),
            p=np.full(t.shape, self.p),
            a=damped_mode(t, self.A1, self.g1, self.f1, self.phi1),
            b=damped_mode(t, self.A2, self.g2, self.f2, self.phi2),
        )

    def offset_mm(self, radius_mm: float) -> float:
        """The steady centre displacement d + p R (mm): what a report's ``offset_mm`` and the truth's hold."""
        return float(self.d + self.p * radius_mm)

    def as_dict(self) -> dict[str, float]:
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}


@dataclass(frozen=True)
class CoefficientRanges:
    """Uniform sampling ranges for (d, p, a, b): the shapes renders and fits are drawn from.

    Defaults keep the sun's highlight on the fluid and informative for the example
    scene: slopes up to ~0.2, rim within +/-50 um of the outlet plane.
    """

    d: tuple[float, float] = (-0.05, 0.05)
    p: tuple[float, float] = (-0.2, 0.2)
    a: tuple[float, float] = (-0.03, 0.03)
    b: tuple[float, float] = (-0.015, 0.015)

    def bounds(self) -> np.ndarray:
        """Shape (4, 2): low and high of d, p, a, b."""
        return np.array([self.d, self.p, self.a, self.b], dtype=np.float64)

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Shape (n, 4): independent uniform draws of d, p, a, b."""
        lo, hi = self.bounds().T
        return rng.uniform(lo, hi, size=(n, 4))
