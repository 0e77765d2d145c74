"""Matrix-pencil estimate of damped complex exponentials: the starting point of the window fit.

Hua & Sarkar (1990), "Matrix pencil method for estimating parameters of exponentially
damped/undamped sinusoids in noise", IEEE Trans. ASSP 38(5):814-824. A series
``x[n] = sum_k h_k z_k^n`` (n = 0..N-1) has a Hankel matrix of rank K; the K dominant right
singular vectors are shift-invariant, and the eigenvalues of that shift are the poles ``z_k``.
A damped sinusoid ``A exp(-g n) cos(w n + phi)`` is the pole pair ``exp(-g +- i w)``.

Compiled (numba) like :mod:`service.analysis.kernels`: in numpy its dozen small calls were a
quarter of a window's fit.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: log|z| is kept in [-_MAX_LOG_DECAY, _MAX_LOG_GROWTH / N]: no overflow, no 0 * inf, in z^n.
_MAX_LOG_DECAY = 50.0
_MAX_LOG_GROWTH = 600.0

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@njit(**_JIT)
def powers(poles: np.ndarray, n: int) -> np.ndarray:
    """Vandermonde matrix ``z_k ** j`` of shape (n, K), with |z| clipped so that it stays finite."""
    out = np.empty((n, poles.size), np.complex128)
    for k in range(poles.size):
        z = poles[k] if poles[k] != 0 else np.exp(-_MAX_LOG_DECAY) + 0j
        log_z = np.log(z)
        log_r = min(max(log_z.real, -_MAX_LOG_DECAY), _MAX_LOG_GROWTH / max(n - 1, 1))
        step, power = np.exp(log_r + 1j * log_z.imag), 1.0 + 0j
        for j in range(n):  # one complex product a sample, not an exp: ~n ulp of rounding, for ranking poles
            out[j, k] = power
            power *= step
    return out


@njit(**_JIT)
def energy(poles: np.ndarray, amplitudes: np.ndarray, n: int) -> np.ndarray:
    """sum_j |h_k z_k^j|^2 over n samples, shape (K,): how much of the series each pole explains;
    0 for a pole with no amplitude (not 0 * inf)."""
    out = np.zeros(poles.size)
    for k in range(poles.size):
        weight = abs(amplitudes[k]) ** 2
        if weight == 0:
            continue
        r2 = abs(poles[k]) ** 2
        geometric = n if abs(r2 - 1.0) <= 1e-8 else (1.0 - r2**n) / (1.0 - r2)
        out[k] = weight * geometric
    return out


@njit(**_JIT)
def exponentials(x: np.ndarray, pencil: int, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Poles and amplitudes (K,), complex, of the ``order`` exponentials spanning the dominant signal
    subspace of the finite real series ``x`` (N >= 3), with ``pencil`` Hankel rows (clipped to [1, N - 2])."""
    size = x.size
    rows = min(max(pencil, 1), size - 2)
    hankel = np.empty((size - rows, rows + 1))
    for i in range(size - rows):
        hankel[i, :] = x[i : i + rows + 1]
    hankel /= max(np.abs(x).max(), 1e-300)  # its square finite for any finite x
    _, vectors = np.linalg.eigh(hankel.T @ hankel)  # ascending: the right singular vectors, the last dominant
    order = min(max(order, 1), min(size - rows, rows))
    v = np.ascontiguousarray(vectors[:, ::-1][:, :order])  # (L + 1, K): spans [z^0 .. z^L]
    shift = np.linalg.lstsq(np.ascontiguousarray(v[:-1]), np.ascontiguousarray(v[1:]))[0]  # v[1:] = v[:-1] @ shift
    poles = np.linalg.eigvals(shift.astype(np.complex128))  # complex: a real shift has complex eigenvalues
    basis = powers(poles, size)
    largest = np.empty(poles.size)  # each column scaled to its largest |z^j| (up to e^600): its square stays finite
    for k in range(poles.size):
        largest[k] = np.abs(basis[:, k]).max()
        basis[:, k] /= largest[k]
    gram = np.conj(basis.T) @ basis  # the amplitudes rank the poles only: their normal equations suffice
    amplitudes = np.linalg.lstsq(gram, np.conj(basis.T) @ x.astype(np.complex128))[0] / largest
    return poles, amplitudes


@njit(**_JIT)
def damped_sinusoids(x: np.ndarray, pencil: int, order: int, min_cycles: float) -> tuple[np.ndarray, np.ndarray]:
    """Angular frequency w (rad/sample, in (0, pi]) and decay g (1/sample) of each pole pair of ``x``, most
    energetic first; two arrays of shape (P,).

    Only poles in the upper half plane count (their conjugates carry the same mode), and only those
    turning at least ``min_cycles`` over the N samples: slower pairs stand in for an offset or a trend."""
    poles, amplitudes = exponentials(x, pencil, order)
    upper = np.angle(poles) * x.size >= 2 * np.pi * min_cycles
    kept = poles[upper]
    ranking = np.argsort(-energy(kept, amplitudes[upper], x.size), kind="mergesort")
    kept = kept[ranking]
    return np.angle(kept), -np.log(np.abs(kept))
