"""Matrix-pencil estimate of damped complex exponentials: the starting point of the window fit.

Hua & Sarkar (1990), "Matrix pencil method for estimating parameters of exponentially
damped/undamped sinusoids in noise", IEEE Trans. ASSP 38(5):814-824. A series
``x[n] = sum_k h_k z_k^n`` (n = 0..N-1) has a Hankel matrix of rank K; the K dominant right
singular vectors are shift-invariant, and the eigenvalues of that shift are the poles ``z_k``.
A damped sinusoid ``A exp(-g n) cos(w n + phi)`` is the pole pair ``exp(-g +- i w)``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import ArrayLike

#: log|z| is kept in [-_MAX_LOG_DECAY, _MAX_LOG_GROWTH / N]: no overflow, no 0 * inf, in z^n.
_MAX_LOG_DECAY = 50.0
_MAX_LOG_GROWTH = 600.0


@dataclass(frozen=True)
class Exponentials:
    """``x[n] ~ sum_k amplitudes[k] * poles[k] ** n``; each an array of shape (K,), complex."""

    poles: np.ndarray
    amplitudes: np.ndarray
    length: int  # N, the number of samples they were fitted to

    def energy(self) -> np.ndarray:
        """sum_n |h_k z_k^n|^2 over the N samples, shape (K,): how much of the series each pole explains."""
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            r2 = np.abs(self.poles) ** 2
            geometric = np.where(np.isclose(r2, 1.0), self.length, (1 - r2**self.length) / (1 - r2))
        weight = np.abs(self.amplitudes) ** 2
        return np.where(weight > 0, weight * geometric, 0.0)  # a pole with no amplitude explains nothing (not 0 * inf)

    def damped_sinusoids(self, min_cycles: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
        """Angular frequency w (rad/sample, in (0, pi]) and decay g (1/sample) of each pole pair, most energetic first.

        Only poles in the upper half plane count (their conjugates carry the same mode), and only
        those turning at least ``min_cycles`` over the N samples: slower pairs stand in for an
        offset or a trend. Returns two arrays of shape (P,).
        """
        upper = np.angle(self.poles) * self.length >= 2 * np.pi * min_cycles
        order = np.argsort(-self.energy()[upper], kind="stable")
        z = self.poles[upper][order]
        return np.angle(z), -np.log(np.abs(z))


def powers(poles: np.ndarray, n: int) -> np.ndarray:
    """Vandermonde matrix ``z_k ** j`` of shape (n, K), with |z| clipped so that it stays finite."""
    log_z = np.log(np.where(poles == 0, np.exp(-_MAX_LOG_DECAY), poles).astype(np.complex128))
    log_z = np.clip(log_z.real, -_MAX_LOG_DECAY, _MAX_LOG_GROWTH / max(n - 1, 1)) + 1j * log_z.imag
    with np.errstate(under="ignore"):
        return np.exp(np.outer(np.arange(n), log_z))


class MatrixPencil:
    """The Hankel SVD of one series, computed once, from which estimates of any order are read.

    Parameters
    ----------
    x : array of shape (N,), finite, real or complex, uniformly sampled.
    pencil : pencil parameter L (rows of the shift); Hua & Sarkar's N/3 by default.
    """

    def __init__(self, x: ArrayLike, pencil: int | None = None) -> None:
        x = np.asarray(x)
        if x.ndim != 1 or x.size < 3 or not np.all(np.isfinite(x)):
            raise ValueError("the matrix pencil needs a 1-D finite series of at least 3 samples")
        n = x.size
        self.pencil = int(np.clip(pencil if pencil is not None else n // 3, 1, n - 2))
        hankel = sliding_window_view(x, self.pencil + 1)  # (N - L, L + 1)
        _, self.singular_values, self._vh = np.linalg.svd(hankel, full_matrices=False)
        self._x = x

    @property
    def max_order(self) -> int:
        """The most exponentials the pencil can separate: min(N - L, L)."""
        return min(self._x.size - self.pencil, self.pencil)

    def estimate(self, order: int) -> Exponentials:
        """The ``order`` exponentials spanning the dominant signal subspace, amplitudes by least squares."""
        order = int(np.clip(order, 1, self.max_order))
        v = self._vh[:order].T  # (L + 1, K): spans the rows [z^0 .. z^L] of the Hankel matrix
        shift = np.linalg.lstsq(v[:-1], v[1:], rcond=None)[0]  # (K, K): v[1:] = v[:-1] @ shift
        poles = np.linalg.eigvals(shift)
        amplitudes = np.linalg.lstsq(powers(poles, self._x.size), self._x.astype(np.complex128), rcond=None)[0]
        return Exponentials(poles, amplitudes, self._x.size)
