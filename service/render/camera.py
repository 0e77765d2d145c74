"""The pinhole camera of scene.md: its frame, the rays through the ROI's pixels, projection of world points.

Conventions (scene.md, "Camera"): the camera sits at ``C = distance * direction(az, el)`` and
looks at the world origin; image up is world +z projected onto the image plane, image right
is ``forward x up``; ``fov_deg`` spans ``width_px``; pixels are square; the principal point is
the centre of the ROI. Pixel ``[i, j]`` (row i, column j) has its centre at image coordinates
``(col, row) = (j, i)``, as :mod:`service.render.agreement` measures them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from service.scene import Scene, direction


def camera_frame(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera location (mm), forward and image-up unit vectors, each shape (3,)."""
    cam = scene.camera
    towards_camera = direction(cam.azimuth_deg, cam.elevation_deg)
    forward = -towards_camera
    up = np.array([0.0, 0.0, 1.0]) - forward[2] * forward
    return cam.distance_mm * towards_camera, forward, up / np.linalg.norm(up)


def focal_px(scene: Scene) -> float:
    """Focal length in pixels: half the ROI width over tan(fov / 2)."""
    return 0.5 * scene.camera.width_px / math.tan(math.radians(scene.camera.fov_deg) / 2)


@dataclass(frozen=True)
class Rays:
    """Camera rays through ``supersample`` x ``supersample`` stratified points of every pixel.

    ``origin``: shape (P, 3), each ray's point closest to the world origin (mm), so that
    the ray parameter ``s`` (mm along the ray) stays small near the nozzle and float32 is
    exact enough there; ``direction``: shape (P, 3), unit vectors away from the camera;
    ``camera_s``: shape (P,), the (negative) parameter of the camera centre. Rays are
    ordered (row, sub-row, column, sub-column), so ``(..., P)`` reshapes to
    ``(..., H, ss, W, ss)``.
    """

    origin: np.ndarray
    direction: np.ndarray
    camera_s: np.ndarray
    supersample: int


def pixel_rays(scene: Scene, supersample: int = 1) -> Rays:
    """Rays through the sub-pixel points ``(k + 0.5) / ss`` of each pixel of the ROI (box filter)."""
    cam = scene.camera
    h, w, ss = cam.height_px, cam.width_px, supersample
    location, forward, up = camera_frame(scene)
    right = np.cross(forward, up)
    offsets = (np.arange(ss) + 0.5) / ss - 0.5  # (ss,) within a pixel
    cols = (np.arange(w)[:, None] + offsets).ravel() - (w - 1) / 2  # (W ss,) right of centre
    rows = (np.arange(h)[:, None] + offsets).ravel() - (h - 1) / 2  # (H ss,) below centre
    x = np.broadcast_to(cols[None, :], (h * ss, w * ss)).ravel()
    y = np.broadcast_to(-rows[:, None], (h * ss, w * ss)).ravel()
    d = focal_px(scene) * forward + x[:, None] * right + y[:, None] * up  # (P, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    closest = -(d @ location)  # (P,) parameter of the point nearest the origin
    return Rays(origin=location + closest[:, None] * d, direction=d, camera_s=-closest, supersample=ss)


def project(scene: Scene, points: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Image coordinates (col, row) in pixels of world points of shape (..., 3), in mm.

    Pixel ``[i, j]`` has its centre at (j, i); points behind the camera give meaningless values.
    """
    cam = scene.camera
    location, forward, up = camera_frame(scene)
    right = np.cross(forward, up)
    rel = np.asarray(points, dtype=np.float64) - location
    depth = rel @ forward
    f = focal_px(scene)
    col = f * (rel @ right) / depth + (cam.width_px - 1) / 2
    row = (cam.height_px - 1) / 2 - f * (rel @ up) / depth
    return col, row
