"""Frames of a candidate scene as the camera stores them (before noise), and the loss that compares them to the lab's.

Raw pixel differences are blind to a sharp highlight a few pixels off (no overlap, no gradient), so
frames are compared as a blurred pyramid: each level blurs lab and synthesis alike by sigma (px) and
keeps every ``ceil(sigma)``-th pixel; a square root first evens out bright highlights and dim detail
(and is close to what shot noise makes uniform). Coarse levels see far, fine levels see sharp.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import TYPE_CHECKING

import cv2
import numpy as np

from service.render import Renderer
from service.scene import Scene

if TYPE_CHECKING:
    from service.calibration.fit import Stage

#: Directions over the sun's disc for the fluid: a near-mirror's highlight is the disc's image, and a few
#: directions would draw it as a few dots, which the fit would then explain with a smaller sun.
SUN_SAMPLES = 24
#: Added before the square root: keeps its slope finite at black.
SQRT_FLOOR = 1e-3


def gaussian(frames: np.ndarray, sigma: float) -> np.ndarray:
    """Each frame (K, H, W) blurred by a Gaussian of ``sigma`` px (replicated edges); a copy."""
    out = np.array(frames, dtype=np.float32, copy=True)
    if sigma <= 0:
        return out
    for k in range(len(out)):
        out[k] = cv2.GaussianBlur(out[k], (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
    return out


def stretch(frames: np.ndarray) -> np.ndarray:
    """The square-root intensity scale the loss compares on."""
    return np.sqrt(np.maximum(frames, 0.0) + SQRT_FLOOR)


def pyramid(frames: np.ndarray, sigmas: tuple[float, ...], extra_blur: float = 0.0) -> np.ndarray:
    """(K, P): every level of frames (K, H, W) side by side, each blurred by sqrt(sigma^2 + extra_blur^2),
    subsampled every ceil(sigma) px and weighted by that step (so each level counts about the same)."""
    levels = []
    for sigma in sigmas:
        step = max(1, math.ceil(sigma))
        blurred = gaussian(frames, math.hypot(sigma, extra_blur))[:, step // 2 :: step, step // 2 :: step]
        levels.append(stretch(blurred).reshape(len(frames), -1) * step)
    return np.concatenate(levels, axis=1)


class Synthesis:
    """Renders candidate scenes, keeping the last few renderers (a renderer shades its static scene once, the
    expensive part; the sensor's blur and black level are applied afterwards and never need a new one)."""

    def __init__(
        self,
        supersample: int = 1,
        sun_samples: int = SUN_SAMPLES,
        static_sun_samples: int = 8,
        keep: int = 3,
    ) -> None:
        self.quality = {
            "supersample": supersample,
            "sun_samples": sun_samples,
            "static_sun_samples": static_sun_samples,
            "edge_supersample": 0,  # a stage's (:meth:`use`)
        }
        self._cache: OrderedDict[str, Renderer] = OrderedDict()
        self.keep = keep
        self.builds = 0

    @property
    def rays(self) -> dict[str, int]:
        """The rays per pixel renders are made with (``Renderer``'s ``supersample`` and ``edge_supersample``)."""
        return {name: self.quality[name] for name in ("supersample", "edge_supersample")}

    def use(self, stage: Stage) -> None:
        """Render from now on with the rays of a coarse-to-fine ``stage``."""
        self.quality.update(supersample=stage.supersample, edge_supersample=stage.edge_supersample)

    def renderer(self, scene: Scene) -> Renderer:
        """A renderer of ``scene`` (its sensor block aside), built or reused."""
        data = scene.as_dict()
        data.pop("sensor", None)
        key = repr((sorted(data.items()), sorted(self.quality.items())))  # a new quality needs its own build
        if key not in self._cache:
            self._cache[key] = Renderer(Scene.from_dict(data), threads=None, **self.quality)
            self.builds += 1
            while len(self._cache) > self.keep:
                self._cache.popitem(last=False)
        self._cache.move_to_end(key)
        return self._cache[key]

    def linear(self, scene: Scene, coeffs: np.ndarray) -> np.ndarray:
        """Renders (K, h, w) of per-frame coefficients (K, 4) before the sensor."""
        return self.renderer(scene).render(coeffs)

    def stored(self, scene: Scene, coeffs: np.ndarray) -> np.ndarray:
        """What the camera stores without noise: renders blurred by the sensor's PSF, plus its black level."""
        sensor = scene.sensor
        frames = self.linear(scene, coeffs)
        if sensor is None:
            return frames
        return gaussian(frames, sensor.blur_sigma_px) + np.float32(sensor.offset)

    def levels(self, scene: Scene, coeffs: np.ndarray, sigmas: tuple[float, ...]) -> np.ndarray:
        """(K, P) pyramid of the stored frames: the PSF merged into each level's blur (one blur per level)."""
        blur, offset = (scene.sensor.blur_sigma_px, scene.sensor.offset) if scene.sensor else (0.0, 0.0)
        return pyramid(self.linear(scene, coeffs) + np.float32(offset), sigmas, blur)
