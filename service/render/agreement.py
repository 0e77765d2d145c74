"""How closely two renderers agree on the same frames: highlight position and pixel correlation.

Used to check our renderer against the Blender Cycles reference (``meniscope bench
render``). Two figures per frame pair:

- the highlight centroid: the intensity-weighted centroid of the pixels at or above
  ``threshold`` (output intensity, default :data:`HIGHLIGHT_THRESHOLD`), compared as a
  distance in pixels; a frame with no such pixel has no highlight and is counted, not
  compared;
- the Pearson correlation of the pixels, which ignores gain and offset, alongside
  the least-squares gain g minimising |reference - g * ours|^2; a frame pair where
  either side is constant has no correlation and is counted, not compared.

Nothing here returns NaN: what cannot be measured is left out and counted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from service.errors import MeniscopeError

#: Pixels at or above half of full scale form the highlight: the sun's reflection
#: saturates, while the lit nozzle face stays near albedo * strength / pi (~0.02).
HIGHLIGHT_THRESHOLD = 0.5


@dataclass(frozen=True)
class Highlights:
    """Per-frame highlight of a stack of N frames.

    ``found``: shape (N,), bool, some pixel at or above the threshold.
    ``centroid``: shape (N, 2), (x, y) = (column, row) in pixels, the centre of pixel
    ``[i, j]`` being (j, i); rows where ``found`` is False hold zeros and mean nothing.
    """

    found: np.ndarray
    centroid: np.ndarray


def _as_frames(frames: ArrayLike, name: str) -> np.ndarray:
    arr = np.asarray(frames, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1] == 0 or arr.shape[2] == 0:
        raise MeniscopeError(name, f"expected frames of shape (N, H, W), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise MeniscopeError(name, "frames contain NaN or infinite values")
    return arr


def highlights(frames: ArrayLike, threshold: float = HIGHLIGHT_THRESHOLD) -> Highlights:
    """Intensity-weighted centroid of the pixels >= ``threshold`` in each frame of (N, H, W)."""
    f = _as_frames(frames, "frames")
    weight = np.where(f >= threshold, f, 0.0)  # (N, H, W)
    total = weight.sum(axis=(1, 2))  # (N,)
    found = total > 0
    rows = np.arange(f.shape[1], dtype=np.float64)
    cols = np.arange(f.shape[2], dtype=np.float64)
    safe = np.where(found, total, 1.0)
    x = np.einsum("nhw,w->n", weight, cols) / safe
    y = np.einsum("nhw,h->n", weight, rows) / safe
    return Highlights(found=found, centroid=np.stack([x, y], axis=1))


def correlation_and_gain(ours: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame Pearson correlation and least-squares gain of frame stacks (N, H, W).

    Returns ``valid`` (N,) bool (neither frame constant), and, for the valid frames
    only, ``correlation`` (M,) in [-1, 1] and ``gain`` (M,) with reference ~ gain * ours.
    """
    a = ours.reshape(ours.shape[0], -1)
    b = reference.reshape(reference.shape[0], -1)
    da = a - a.mean(axis=1, keepdims=True)
    db = b - b.mean(axis=1, keepdims=True)
    sa = np.sqrt((da * da).sum(axis=1))
    sb = np.sqrt((db * db).sum(axis=1))
    scale = np.maximum(np.abs(a).max(axis=1), np.abs(b).max(axis=1))
    valid = (sa > 1e-9 * scale * np.sqrt(a.shape[1])) & (sb > 1e-9 * scale * np.sqrt(a.shape[1]))
    r = (da * db).sum(axis=1)[valid] / (sa[valid] * sb[valid])
    gain = (a * b).sum(axis=1)[valid] / (a * a).sum(axis=1)[valid]
    return valid, np.clip(r, -1.0, 1.0), gain


@dataclass(frozen=True)
class Agreement:
    """Per-frame agreement of N frame pairs (ours, reference).

    ``ours_found``, ``reference_found``: shape (N,) bool, a highlight in that frame.
    ``distance_px``: shape (N,), centroid distance where both have a highlight, else 0.
    ``correlated``: shape (N,) bool, neither frame constant.
    ``correlation``, ``gain``: shape (N,), Pearson r and least-squares gain where
    ``correlated``, else 0.
    """

    ours_found: np.ndarray
    reference_found: np.ndarray
    distance_px: np.ndarray
    correlated: np.ndarray
    correlation: np.ndarray
    gain: np.ndarray

    @property
    def both_found(self) -> np.ndarray:
        """Shape (N,) bool: a highlight in both frames, so their centroids compare."""
        return self.ours_found & self.reference_found

    def summary(self) -> dict[str, int | float | None]:
        """The headline figures as plain JSON numbers; None where no frame could be measured."""
        n = int(self.ours_found.shape[0])
        both = self.both_found
        d = self.distance_px[both]
        r = self.correlation[self.correlated]
        g = self.gain[self.correlated]

        def q(x: np.ndarray, pct: float) -> float | None:
            return float(np.percentile(x, pct)) if x.size else None

        return {
            "frames": n,
            "highlight_both": int(both.sum()),
            "highlight_ours_only": int((self.ours_found & ~self.reference_found).sum()),
            "highlight_reference_only": int((~self.ours_found & self.reference_found).sum()),
            "highlight_neither": int((~self.ours_found & ~self.reference_found).sum()),
            "highlight_both_fraction": float(both.mean()) if n else None,
            "centroid_distance_median_px": q(d, 50),
            "centroid_distance_p90_px": q(d, 90),
            "correlated_frames": int(self.correlated.sum()),
            "correlation_median": q(r, 50),
            "correlation_p10": q(r, 10),
            "gain_median": q(g, 50),
        }


def compare(ours: ArrayLike, reference: ArrayLike, threshold: float = HIGHLIGHT_THRESHOLD) -> Agreement:
    """Agreement of two frame stacks of equal shape (N, H, W), frame by frame."""
    a, b = _as_frames(ours, "ours"), _as_frames(reference, "reference")
    if a.shape != b.shape:
        raise MeniscopeError("reference", f"frames of shape {b.shape} do not match ours {a.shape}")
    ha, hb = highlights(a, threshold), highlights(b, threshold)
    both = ha.found & hb.found
    distance = np.where(both, np.linalg.norm(ha.centroid - hb.centroid, axis=1), 0.0)
    valid, r, g = correlation_and_gain(a, b)
    correlation, gain = np.zeros(a.shape[0]), np.zeros(a.shape[0])
    correlation[valid], gain[valid] = r, g
    return Agreement(ha.found, hb.found, distance, valid, correlation, gain)
