"""The dashboard's pictures: the latest frame as the camera saw it, beside a render of its inferred coefficients.

Both are PNGs of the ROI, each stretched to its own brightest pixel (the meniscus shows only sparse
highlights, which at the camera's full scale would be nearly black). The renderer is built on first
use (it shades the static scene once) and draws one frame per request, cheap at one ray per pixel.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from service.errors import MeniscopeError
from service.pipeline.runtime import LatestFrame
from service.scene import Scene


def png(image: np.ndarray) -> bytes:
    """A greyscale image (H, W) of any numeric type as 8-bit PNG bytes, scaled so its maximum is white."""
    x = np.asarray(image, dtype=np.float64)
    peak = float(x.max()) if x.size else 0.0
    scaled = np.zeros(x.shape, np.uint8) if peak <= 0 else np.round(np.clip(x / peak, 0, 1) * 255).astype(np.uint8)
    ok, data = cv2.imencode(".png", scaled)
    if not ok:
        raise MeniscopeError("png", f"OpenCV could not encode a {scaled.shape} image")
    return data.tobytes()


class FrameViews:
    """PNGs of a :class:`LatestFrame` and of the scene rendered from its coefficients."""

    def __init__(self, scene: Scene, scene_path: Path) -> None:
        self.scene, self.scene_path = scene, scene_path
        self._renderer: Any = None  # a service.render.Renderer, made on first use
        self._lock = threading.Lock()  # one render at a time; the renderer is not re-entrant

    def camera(self, frame: LatestFrame) -> bytes:
        return png(frame.pixels)

    def render(self, frame: LatestFrame) -> bytes | None:
        """The render's PNG, or None while another request renders (the first compiles the ray tracer,
        which on a fresh install takes a minute: requests meanwhile are turned away, not queued)."""
        if not self._lock.acquire(blocking=False):
            return None
        try:
            if self._renderer is None:
                from service.render import Renderer  # numba loads only when a render is asked for

                self._renderer = Renderer(self.scene, supersample=1, sun_samples=2, threads=1)
            image = self._renderer.render(np.array([frame.coefficients]))[0]
        finally:
            self._lock.release()
        return png(image)
