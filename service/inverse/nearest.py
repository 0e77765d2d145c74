"""Nearest-neighbour inversion (Price et al. 2022, Sec. 3.2 (a)): a frame's coefficients are those of
the most similar renders in a database of renders with known coefficients.

Frames are compared after the same normalisation the networks use (average pooling by ``factor``,
then zero mean and unit standard deviation per frame), so gain and offset do not matter. Two searches:

- ``exact``: Euclidean distance to every database frame (the paper's choice), as one matrix product
  per batch: |x - y|^2 = |x|^2 + |y|^2 - 2 x.y;
- ``approximate`` (the paper's future work): the frames projected onto the database's first
  ``components`` principal components, searched with OpenCV's FLANN randomised KD-trees; its
  recall@k against ``exact`` is measured by :func:`recall_at_k`.

A database is a folder: ``frames.npy`` (uint8/uint16, as ``meniscope dataset`` writes), ``coeffs.npy``
(N, 4) and ``centre.npy`` (N,), with ``manifest.json`` naming the scene's sha256; it is loaded and
indexed once per process.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from service import blas
from service.errors import MeniscopeError
from service.inverse.base import InverseMethod, InverseOutput
from service.jsonfile import read_schema_json

#: The schema of a dataset folder's manifest.json (``meniscope dataset`` and ``database`` write it last).
DATASET_SCHEMA = "meniscope.dataset/1"
#: Pixels of the pooled frames compared (the networks' input size): 24 x 24 for the 96 x 96 ROI.
POOLED_PX = 24
#: Principal components the approximate search compares.
COMPONENTS = 32
#: FLANN: randomised KD-trees built, and leaves checked per query (more: slower, higher recall).
TREES, CHECKS = 4, 64
#: Database frames normalised per step while indexing (bounds the temporaries' memory).
CHUNK = 8192


def normalise(frames: np.ndarray, factor: int) -> np.ndarray:
    """(N, H, W) frames of any numeric dtype -> (N, H/f * W/f) float32, pooled by ``factor``, zero mean and
    unit standard deviation per frame (a flat frame maps to zeros)."""
    n, h, w = frames.shape
    x = frames.astype(np.float32).reshape(n, h // factor, factor, w // factor, factor).mean(axis=(2, 4))
    x = x.reshape(n, -1)
    x -= x.mean(axis=1, keepdims=True)
    x /= x.std(axis=1, keepdims=True) + 1e-6
    return x


@dataclass(frozen=True)
class Neighbours:
    """The k nearest database entries of N frames: ``index`` (N, k) int64 and ``distance`` (N, k), nearest first."""

    index: np.ndarray
    distance: np.ndarray


class NearestDatabase:
    """Renders with known coefficients, normalised and indexed for exact and approximate k-NN search."""

    def __init__(
        self,
        frames: np.ndarray,
        coeffs: np.ndarray,
        centre: np.ndarray,
        components: int = COMPONENTS,
        where: str = "database",
    ) -> None:
        if frames.ndim != 3 or len(frames) != len(coeffs) or len(frames) != len(centre) or len(frames) < 2:
            raise MeniscopeError(
                where,
                f"needs >= 2 frames with one coefficient row and centre each, got "
                f"{frames.shape}, {np.shape(coeffs)}, {np.shape(centre)}",
            )
        h, w = frames.shape[1:]
        self.factor = max(1, h // POOLED_PX)
        if h % self.factor or w % self.factor:
            raise MeniscopeError(where, f"frames of {w}x{h} do not pool by {self.factor}")
        self.shape = (h, w)
        self.coeffs = np.asarray(coeffs, np.float64)
        self.centre = np.asarray(centre, np.float64)
        self.vectors = np.concatenate(
            [normalise(np.asarray(frames[i : i + CHUNK]), self.factor) for i in range(0, len(frames), CHUNK)]
        )  # (N, P) float32
        self.sq_norms = np.einsum("np,np->n", self.vectors, self.vectors)
        sample = self.vectors[:: max(1, len(self.vectors) // 20000)]
        self.mean = sample.mean(axis=0)
        _, _, vt = np.linalg.svd(sample - self.mean, full_matrices=False)
        self.basis = np.ascontiguousarray(vt[: min(components, vt.shape[0])].T)  # (P, C)
        projected = np.ascontiguousarray((self.vectors - self.mean) @ self.basis, dtype=np.float32)
        self._flann = cv2.flann_Index(projected, {"algorithm": 1, "trees": TREES})  # 1: FLANN_INDEX_KDTREE

    @classmethod
    def load(cls, folder: str | Path, components: int = COMPONENTS) -> NearestDatabase:
        """A database folder (``meniscope dataset`` output): frames.npy, coeffs.npy, centre.npy."""
        folder = Path(folder)
        arrays = []
        for name in ("frames.npy", "coeffs.npy", "centre.npy"):
            try:
                arrays.append(np.load(folder / name, mmap_mode="r"))
            except FileNotFoundError:
                raise MeniscopeError(
                    folder / name, "missing: not a render database (make one with `meniscope dataset`)"
                ) from None
            except ValueError as exc:
                raise MeniscopeError(folder / name, f"not a readable .npy file: {exc}") from None
        return cls(*arrays, components=components, where=str(folder))

    def __len__(self) -> int:
        return len(self.coeffs)

    @staticmethod
    def scene_sha256(folder: str | Path) -> str:
        """The sha256 of the scene a database folder's renders were made for, from its manifest."""
        path = Path(folder) / "manifest.json"
        manifest = read_schema_json(
            path,
            DATASET_SCHEMA,
            "not a render database from `meniscope database` "
            "(or `dataset`), or its rendering did not finish: its scene cannot be checked",
        )
        sha = manifest.get("scene_sha256")
        if not isinstance(sha, str):
            raise MeniscopeError(path, "names no scene_sha256: the scene its renders were made for is unknown")
        return sha

    def search(self, frames: np.ndarray, k: int = 10, exact: bool = True, batch: int = 256) -> Neighbours:
        """The k nearest database entries of each of N frames (N, H, W) as stored."""
        frames = np.asarray(frames)
        if frames.ndim != 3 or frames.shape[1:] != self.shape:
            raise MeniscopeError(
                "frames", f"shape {frames.shape} is not (N, {self.shape[0]}, {self.shape[1]}), the database's"
            )
        k = int(min(max(k, 1), len(self)))
        index = np.empty((len(frames), k), np.int64)
        distance = np.empty((len(frames), k), np.float64)
        with blas.threads(blas.usable_cores()):  # the one large product: on every core, where an analysis holds one
            for start in range(0, len(frames), batch):
                part = slice(start, start + batch)
                x = normalise(frames[part], self.factor)
                if exact:
                    d2 = self.sq_norms[None, :] - 2.0 * (x @ self.vectors.T) + np.einsum("np,np->n", x, x)[:, None]
                    found = np.argpartition(d2, k - 1, axis=1)[:, :k]
                else:
                    q = np.ascontiguousarray((x - self.mean) @ self.basis, dtype=np.float32)
                    found, _ = self._flann.knnSearch(q, k, params={"checks": CHECKS})
                # distances of the k found, directly (the expansion above cancels in float32), nearest first
                dist = np.linalg.norm(self.vectors[found].astype(np.float64) - x[:, None, :], axis=2)
                order = dist.argsort(axis=1, kind="stable")
                index[part] = np.take_along_axis(found, order, axis=1)
                distance[part] = np.take_along_axis(dist, order, axis=1)
        return Neighbours(index=index, distance=distance)


def recall_at_k(approximate: Neighbours, exact: Neighbours) -> float:
    """Mean fraction of the exact k nearest that the approximate search also returned."""
    hits = [len(np.intersect1d(a, e)) for a, e in zip(approximate.index, exact.index)]
    return float(np.mean(hits) / exact.index.shape[1])


class NearestMethod(InverseMethod):
    """The per-frame nearest-neighbour inverse: the coefficients and D(0, t) of the single nearest render."""

    def __init__(self, database: NearestDatabase, exact: bool = True) -> None:
        self.database, self.exact = database, exact
        self.name = "nearest" if exact else "nearest-approx"

    def infer(self, frames: np.ndarray) -> InverseOutput:
        nearest = self.database.search(frames, k=1, exact=self.exact).index[:, 0]
        return InverseOutput(coefficients=self.database.coeffs[nearest], centre=self.database.centre[nearest])
