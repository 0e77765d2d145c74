"""The sensor's noise from the lab's own frames: static pixels' temporal variance against their mean.

Outside the bore nothing moves, so a static pixel's spread over time is the camera's noise alone:
``var = read^2 + (mean - black) / full_well`` in fractions of full scale (shot noise grows with the
signal, read noise does not; a quantisation step adds 1/12 of a step squared).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Most refits of the noise line without the pixels far above it (it settles in four or five).
ROUNDS = 20
#: Read noise (quantisation steps) below which the rounding's variance is not the uniform step^2 / 12 the fit takes
#: off (Sheppard's correction holds from about half a step of Gaussian noise), so the video does not tell the noise.
MEASURABLE_STEPS = 0.5


@dataclass(frozen=True)
class NoiseFit:
    """Full well (electrons at full scale, 0 where shot noise is not seen), read noise (electrons, or as a
    fraction of full scale when the full well is unknown), and the pixels it rests on."""

    full_well_e: float
    read_noise_e: float
    read_noise_fraction: float
    pixels: int
    signal_span: float

    def measured(self, full_scale: float) -> bool:
        """Whether the still pixels' noise could be told: their read noise at least :data:`MEASURABLE_STEPS` of a
        quantisation step (an 8-bit camera's can lie under it)."""
        return self.read_noise_fraction * full_scale >= MEASURABLE_STEPS

    def sigma(self, signal: np.ndarray, full_scale: float) -> np.ndarray:
        """The temporal noise (fraction of full scale) this model expects of a static pixel ``signal`` above
        black: read noise, shot noise where the full well is known, and the quantisation step."""
        shot = np.maximum(signal, 0.0) / self.full_well_e if self.full_well_e > 0 else 0.0
        return np.sqrt(self.read_noise_fraction**2 + shot + 1.0 / (12.0 * full_scale**2))


def fit_noise(stack: np.ndarray, static: np.ndarray, black: float, full_scale: float) -> NoiseFit:
    """Noise of frames ``stack`` (S, h, w) in fractions of full scale over the ``static`` mask (h, w) bool."""
    values = stack[:, static].astype(np.float64)  # (S, P)
    mean, var = values.mean(axis=0), values.var(axis=0, ddof=1)
    var = var - 1.0 / (12.0 * full_scale**2)
    signal = np.maximum(mean - black, 0.0)
    # a line, refitted without the pixels far above it (where the fluid's shadow or a reflection reaches now and
    # then, a static pixel is not static) until the pixels kept stay the same: a few dozen such pixels of a dim
    # camera's thousands pull the first lines' slope far up (docs/calibration.md, "One kind at a time")
    keep = np.ones(len(var), bool)
    for _ in range(ROUNDS):
        A = np.stack([np.ones(keep.sum()), signal[keep]], axis=1)
        (intercept, slope), *_ = np.linalg.lstsq(A, var[keep], rcond=None)
        resid = var - (intercept + slope * signal)
        kept, keep = keep, resid < 4 * 1.4826 * np.median(np.abs(resid[keep])) + 1e-12
        if np.array_equal(kept, keep):
            break
    read = float(np.sqrt(max(intercept, 0.0)))
    if slope <= 0:
        return NoiseFit(0.0, 0.0, read, int(keep.sum()), float(np.ptp(signal)))
    full_well = float(1.0 / slope)
    return NoiseFit(full_well, read * full_well, read, int(keep.sum()), float(np.ptp(signal)))
