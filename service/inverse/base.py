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
    """

    coefficients: np.ndarray
    centre: np.ndarray

    def as_coefficients(self) -> Coefficients:
        return Coefficients.from_array(self.coefficients)


class InverseMethod(ABC):
    """Frames of the scene's ROI -> per-frame coefficients; one instance per scene and model."""

    #: short stable name used in settings, REPORT.json "method" and benchmarks
    name: str

    @abstractmethod
    def infer(self, frames: np.ndarray) -> InverseOutput:
        """Infer a batch.

        frames : uint8 or uint16 (N, H, W), the scene's ROI as stored (no scaling),
                 rows in display order; H, W = scene.camera.height_px, width_px.
        """
