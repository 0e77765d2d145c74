"""The camera between a linear render and stored pixels: optics, gain, sensor noise, quantisation.

One implementation serves ``meniscope simulate`` (fixed settings, :class:`CameraEffects`) and the
training set's augmentations (settings drawn per frame, :class:`EffectRanges`); scene.md says the
inverse models must be robust to exactly these: gain, offset, noise and blur.

Per frame, with ``x`` the linear render in [0, 1] (scene.md, "Camera") and ``M = 2**bit_depth - 1``:

    y = PSF_sigma * shift_(dx, dy) * x          optics, on the pixel grid, replicated edges
    s = clip(gain * y, 0, 1)                    fraction of the full well (saturates at 1)
    e ~ Poisson(s * full_well_e)                shot noise (none when full_well_e == 0)
    DN = round(M * (e / full_well_e + offset) + read_noise_dn * z),  z ~ N(0, 1)
    pixel = clip(DN, 0, M)                      uint8 (8 bits) or uint16 (10, 12, 16 bits)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from service.noise_presets import NOISE_PRESETS

BitDepth = Literal[8, 10, 12, 16]

#: Below this many expected electrons shot noise is drawn exactly from a Poisson law; above it
#: from its normal approximation (skewness 1/sqrt(lam) < 0.1), which is ~8x faster to draw.
POISSON_EXACT_BELOW_E = 100.0

#: Frames per internal block: small enough that the float32 temporaries stay in cache and
#: are reused by the allocator instead of being page-faulted in afresh (measured ~3x faster).
_BLOCK_FRAMES = 32

_Finite = Annotated[float, Field(allow_inf_nan=False)]
_Range = tuple[_Finite, _Finite]


def pixel_dtype(bit_depth: int) -> np.dtype:
    """Storage type of a bit depth: uint8 for 8 bits, uint16 for 10, 12 and 16."""
    return np.dtype(np.uint8 if bit_depth <= 8 else np.uint16)


@dataclass(frozen=True)
class FrameEffects:
    """Camera settings for a batch of N frames, one value per frame.

    gain          : (N,) multiplies linear intensity (exposure, contrast)
    offset        : (N,) black level, fraction of full scale, added after the sensor
    blur_sigma_px : (N,) standard deviation of the Gaussian PSF, pixels
    shift_px      : (N, 2) sub-pixel image shift (right, down), pixels
    full_well_e   : (N,) electrons at full scale; 0 disables shot noise
    read_noise_dn : (N,) standard deviation of the Gaussian read noise, in output DN
    """

    gain: np.ndarray
    offset: np.ndarray
    blur_sigma_px: np.ndarray
    shift_px: np.ndarray
    full_well_e: np.ndarray
    read_noise_dn: np.ndarray

    def __len__(self) -> int:
        return int(self.gain.shape[0])

    def __getitem__(self, frames: slice) -> FrameEffects:
        """The settings of a slice of the frames."""
        return FrameEffects(**{k: v[frames] for k, v in vars(self).items()})


class CameraEffects(BaseModel):
    """Fixed camera settings for every frame of a recording; the defaults are an ideal camera.

    ``bit_depth`` fixes the stored range (``2**bit_depth - 1`` at full scale) and the unit of
    ``read_noise_dn``. Build realistic settings with :func:`noise_preset`.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    gain: Annotated[float, Field(ge=0, le=1e6, allow_inf_nan=False)] = 1.0
    offset: Annotated[float, Field(ge=-1, le=1, allow_inf_nan=False)] = 0.0
    blur_sigma_px: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 0.0
    shift_px: tuple[
        Annotated[float, Field(ge=-8, le=8, allow_inf_nan=False)],
        Annotated[float, Field(ge=-8, le=8, allow_inf_nan=False)],
    ] = (0.0, 0.0)
    full_well_e: Annotated[float, Field(ge=0, le=1e9, allow_inf_nan=False)] = 0.0
    read_noise_dn: Annotated[float, Field(ge=0, le=1e5, allow_inf_nan=False)] = 0.0
    bit_depth: BitDepth = 8

    def per_frame(self, n: int) -> FrameEffects:
        """These settings repeated for ``n`` frames."""
        full = lambda v: np.full(n, v, dtype=np.float64)
        return FrameEffects(
            gain=full(self.gain),
            offset=full(self.offset),
            blur_sigma_px=full(self.blur_sigma_px),
            shift_px=np.tile(np.asarray(self.shift_px, dtype=np.float64), (n, 1)),
            full_well_e=full(self.full_well_e),
            read_noise_dn=full(self.read_noise_dn),
        )

    def apply(self, linear: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Stored pixels (N, H, W), uint8 or uint16, of linear renders (N, H, W) in [0, 1]."""
        return apply_effects(linear, self.per_frame(len(linear)), self.bit_depth, rng)


def noise_preset(name: str, bit_depth: BitDepth) -> CameraEffects:
    """The named preset of :data:`NOISE_PRESETS` at ``bit_depth`` (read noise converted to DN)."""
    full_well, read_e, sigma, offset = NOISE_PRESETS[name]
    return sensor_effects(offset, sigma, full_well, read_e, bit_depth)


def sensor_effects(
    offset: float, blur_sigma_px: float, full_well_e: float, read_noise_e: float, bit_depth: BitDepth
) -> CameraEffects:
    """A calibrated sensor (a scene's ``sensor`` block, read noise in electrons) at ``bit_depth``."""
    read_dn = read_noise_e / full_well_e * (2**bit_depth - 1) if full_well_e else 0.0
    return CameraEffects(
        full_well_e=full_well_e, read_noise_dn=read_dn, blur_sigma_px=blur_sigma_px, offset=offset, bit_depth=bit_depth
    )


class EffectRanges(BaseModel):
    """Augmentation ranges: each frame draws its own settings, uniformly (full well log-uniformly).

    Defaults span a camera a little worse and a little better than the "lab" preset, so that a
    model trained on them does not learn one exposure, black level, noise or focus.
    ``read_noise_dn`` is in DN of the bit depth the frames are stored at.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    gain: _Range = (0.6, 1.5)
    offset: _Range = (-0.01, 0.04)
    blur_sigma_px: _Range = (0.0, 1.2)
    shift_px: Annotated[float, Field(ge=0, le=8, allow_inf_nan=False)] = 0.5
    full_well_e: _Range = (3000.0, 40000.0)
    read_noise_dn: _Range = (0.0, 1.5)

    def sample(self, n: int, rng: np.random.Generator) -> FrameEffects:
        """Independent draws for ``n`` frames (shift uniform in +/- ``shift_px`` on each axis)."""
        uniform = lambda lohi: rng.uniform(*lohi, size=n)
        lo, hi = np.log(self.full_well_e)
        return FrameEffects(
            gain=uniform(self.gain),
            offset=uniform(self.offset),
            blur_sigma_px=uniform(self.blur_sigma_px),
            shift_px=rng.uniform(-self.shift_px, self.shift_px, size=(n, 2)),
            full_well_e=np.exp(rng.uniform(lo, hi, size=n)),
            read_noise_dn=uniform(self.read_noise_dn),
        )


def _sampled_gaussian(m: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Gaussian PSF at integer offsets ``m`` (N, K), normalised over the integers; ``sigma`` (N, 1), 0: impulse."""
    positive = sigma > 0
    safe = np.where(positive, sigma, 1.0)
    reach = int(np.ceil(6.0 * sigma.max())) + 1
    lattice = np.arange(-reach, reach + 1)
    norm = np.exp(-0.5 * (lattice / safe) ** 2).sum(axis=-1, keepdims=True)
    return np.where(positive, np.exp(-0.5 * (m / safe) ** 2) / norm, m == 0)


def _kernels(shift: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """1-D correlation kernels (N, K), K odd, centre tap K // 2: a shift by ``shift`` px, then the PSF.

    A shift ``n + f`` (n integer, 0 <= f < 1) is linear interpolation (tap ``-n``: 1 - f, tap
    ``-n - 1``: f), which blurs by at most 0.25 px^2 more; composed with the sampled Gaussian ``g``
    the taps are ``w_j = (1 - f) g(j + n) + f g(j + n + 1)``.
    """
    half = int(np.ceil(np.abs(shift).max())) + 1 + int(np.ceil(4.0 * sigma.max()))
    taps = np.arange(-half, half + 1, dtype=np.float64)  # (K,)
    n = np.floor(shift)[:, None]
    f = shift[:, None] - n
    s = sigma[:, None]
    return (1.0 - f) * _sampled_gaussian(taps + n, s) + f * _sampled_gaussian(taps + n + 1.0, s)


def optics(linear: np.ndarray, effects: FrameEffects) -> np.ndarray:
    """Sub-pixel shift and Gaussian PSF of each frame, replicated edges: float32 (N, H, W) of (N, H, W)."""
    out = linear.astype(np.float32, copy=True)
    moved = (effects.blur_sigma_px > 0) | np.any(effects.shift_px != 0, axis=1)
    idx = np.flatnonzero(moved)
    if idx.size == 0:
        return out
    sigma = effects.blur_sigma_px[idx]
    kx = _kernels(effects.shift_px[idx, 0], sigma).astype(np.float32)
    ky = _kernels(effects.shift_px[idx, 1], sigma).astype(np.float32)
    for row, i in enumerate(idx):  # one OpenCV call per frame, each vectorised over its pixels
        out[i] = cv2.sepFilter2D(out[i], -1, kx[row], ky[row], borderType=cv2.BORDER_REPLICATE)
    return out


def apply_effects(
    linear: np.ndarray, effects: FrameEffects, bit_depth: BitDepth, rng: np.random.Generator
) -> np.ndarray:
    """Apply the camera model (module docstring) to a batch of linear renders.

    Parameters
    ----------
    linear : ndarray of shape (N, H, W), float, linear intensity in [0, 1] (finite)
    effects : per-frame settings, N of each
    bit_depth : 8, 10, 12 or 16
    rng : the only source of randomness; the same generator state gives the same pixels

    Returns
    -------
    ndarray of shape (N, H, W), uint8 (8 bits) or uint16, values in [0, 2**bit_depth - 1]
    """
    linear = np.asarray(linear)
    if linear.ndim != 3 or len(effects) != linear.shape[0]:
        raise ValueError(f"need frames (N, H, W) and N per-frame settings, got {linear.shape} and {len(effects)}")
    if not np.isfinite(linear).all():
        raise ValueError("linear frames contain NaN or infinity")
    out = np.empty(linear.shape, dtype=pixel_dtype(bit_depth))
    for start in range(0, len(out), _BLOCK_FRAMES):
        block = slice(start, start + _BLOCK_FRAMES)
        out[block] = _sensor(optics(linear[block], effects[block]), effects[block], bit_depth, rng)
    return out


def _sensor(optical: np.ndarray, effects: FrameEffects, bit_depth: BitDepth, rng: np.random.Generator) -> np.ndarray:
    """Gain, saturation, shot and read noise, black level and rounding of optical frames (N, H, W) float32."""
    top = float(2**bit_depth - 1)
    col = lambda v: np.asarray(v, dtype=np.float32)[:, None, None]
    signal = optical
    signal *= col(effects.gain)
    np.clip(signal, 0.0, 1.0, out=signal)  # fraction of the full well, saturating
    dn = signal * np.float32(top)
    dn += col(top * effects.offset)
    well = effects.full_well_e
    if np.any(well > 0) or np.any(effects.read_noise_dn > 0):
        z = rng.standard_normal(signal.shape, dtype=np.float32)
        # shot noise (normal approximation) and read noise are independent Gaussians: one draw
        dn_per_electron = np.divide(top, well, out=np.zeros_like(well), where=well > 0)  # (N,)
        sigma = signal * col(top * dn_per_electron)  # variance of the shot noise, DN^2
        sigma += col(effects.read_noise_dn**2)
        np.sqrt(sigma, out=sigma)
        dn += sigma * z
        # few electrons: exact Poisson shot noise instead; z keeps the read noise
        threshold = np.divide(POISSON_EXACT_BELOW_E, well, out=np.full_like(well, -1.0), where=well > 0)
        dim = (signal > 0) & (signal < col(threshold))
        if dim.any():
            frame = np.nonzero(dim)[0]
            electrons = rng.poisson(signal[dim] * well[frame])
            dn[dim] = (
                electrons * dn_per_electron[frame] + top * effects.offset[frame] + effects.read_noise_dn[frame] * z[dim]
            )
    np.rint(dn, out=dn)
    return np.clip(dn, 0.0, top, out=dn)
