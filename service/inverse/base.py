"""The seam every inverse method implements (ARCHITECTURE.md, "InverseMethod")."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from service.physics import Coefficients


@dataclass(frozen=True)
class InverseOutput:
    """What a method infers for a batch of N frames.

    coefficients : float64 (N, 4), columns d (mm), p (-), a (mm), b (mm) of Eq. 1
    centre       : float64 (N,), centre displacement D(0, t) in mm
    latent       : float32 (N, 10), the network's encoder mean (:data:`service.inverse.manifest.LATENT`), or None
                   for a method or graph without one
    """

    coefficients: np.ndarray
    centre: np.ndarray
    latent: np.ndarray | None = None

    def as_coefficients(self) -> Coefficients:
        return Coefficients.from_array(self.coefficients)


class InverseMethod(ABC):
    """Frames of the scene's ROI -> per-frame coefficients; one instance per scene and model."""

    #: short stable name used in settings, REPORT.json "method" and benchmarks
    name: str
    #: f > 0 where the method's input (:meth:`infer_prepared`'s) is its frames' f x f block means, float32 (N, 1, H/f,
    #: W/f), so that the pass that measures the frames' pixels makes it too; 0 where :meth:`prepare` makes it.
    pooling: int = 0
    #: Where ``pooling``: whether those block means are then standardised frame by frame
    #: (:func:`service.inverse.pooling.standardise`), in the same pass.
    standardised: bool = False

    @abstractmethod
    def infer(self, frames: np.ndarray) -> InverseOutput:
        """Infer a batch.

        frames : uint8 or uint16 (N, H, W), the scene's ROI as stored (no scaling),
                 rows in display order; H, W = scene.camera.height_px, width_px.
        """

    def check(self, frames: np.ndarray) -> None:
        """Raise :class:`~service.errors.MeniscopeError` where ``frames`` (N, H, W) cannot be the method's frames;
        any can by default."""
        return None

    def prepare(self, frames: np.ndarray) -> np.ndarray:
        """The method's input made of a batch of ROI frames (N, ...), per frame: what can be done where the frames are
        read and measured, so that the thread that infers takes less (a graph's pooled frames); the frames
        themselves by default."""
        return frames

    def infer_prepared(self, inputs: np.ndarray) -> InverseOutput:
        """:meth:`infer` of the frames :meth:`prepare` made ``inputs`` of (concatenated along their first axis)."""
        return self.infer(inputs)
