"""The artifact spheres from their glints in the lab's static image: found, placed on the nozzle face, sized.

A defect is a small sphere on the bottom face (centre at z = 0). Its glint is where its normal bisects the
view and the light, ``glint = centre + radius h`` with ``h`` the unit half-vector, so a glint seen at a
pixel fixes the centre once the radius is known: the ray through the pixel meets the plane
``z = radius h_z`` at the glint. The radius follows from the glint's flux (a mirror ball's radiant
intensity grows as radius^2; shading.py), measured against a render of a sphere of known size.
"""

from __future__ import annotations

import cv2
import numpy as np

from service.calibration.noise import NoiseFit
from service.render import Renderer
from service.render.camera import camera_frame, focal_px, project
from service.scene import Scene, direction

#: Radius (mm) the first placement assumes; the flux then rescales it.
START_RADIUS_MM = 0.012
#: Half-size (px) of the square over which a glint's flux is summed.
FLUX_HALF_PX = 2
#: A glint must stand this many noise sigmas above the static model.
DETECT_SIGMAS = 6.0
#: A pixel is still when its robust temporal spread is within this many of the noise model's sigma at its level,
#: or within STILL_FRACTION of its level above black (a glint by the rim that the fluid shades now and then).
STILL_SIGMAS = 3.0
STILL_FRACTION = 0.25
#: A glint must also stand this fraction of the face's own brightness above the model: where two renderers draw
#: the face's edges (Blender and ours), their leftovers there are fainter (docs/calibration.md, calib4).
CONTRAST = 0.4
#: Glints are not looked for this close (px) to the face's outline.
OUTLINE_PX = 2


def pixel_ray(scene: Scene, col: float | np.ndarray, row: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre (3,) and unit directions (..., 3) of the rays through image points (col, row) of the ROI."""
    cam = scene.camera
    location, forward, up = camera_frame(scene)
    right = np.cross(forward, up)
    x = np.asarray(col, dtype=np.float64)[..., None] - (cam.width_px - 1) / 2
    y = np.asarray(row, dtype=np.float64)[..., None] - (cam.height_px - 1) / 2
    d = focal_px(scene) * forward + x * right - y * up
    return location, d / np.linalg.norm(d, axis=-1, keepdims=True)


def face_pixels(scene: Scene) -> np.ndarray:
    """Pixels (h, w) bool whose ray meets the plane z = 0 on the nozzle's bottom face (R < r < outer radius) at
    least OUTLINE_PX from the face's outline: where a defect's glint can be told from the leftovers of an outline
    drawn a fraction of a pixel off (by the calibrated pose, ROI and blur, or by another renderer)."""
    cam, nz = scene.camera, scene.nozzle
    rows, cols = np.mgrid[0 : cam.height_px, 0 : cam.width_px]
    location, d = pixel_ray(scene, cols.ravel().astype(float), rows.ravel().astype(float))
    t = -location[2] / d[..., 2]
    r = np.hypot(*(location[:2, None] + t * d[..., :2].T)).reshape(cam.height_px, cam.width_px)
    inside = cv2.erode((r < nz.outer_radius_mm).astype(np.uint8), np.ones((2 * OUTLINE_PX + 1,) * 2, np.uint8))
    return (r > nz.radius_mm) & inside.astype(bool)


def still_pixels(stack: np.ndarray, noise: NoiseFit, black: float, full_scale: float) -> np.ndarray:
    """Pixels (h, w) bool of ``stack`` (S, h, w) whose robust temporal spread (1.4826 MAD, blind to a fluid
    that covers them now and then) is the camera's noise alone: where a static glint can be told from the
    fluid's moving highlights, however near the bore (the fluid's reach in the model is far wider)."""
    median = np.median(stack, axis=0)
    spread = 1.4826 * np.median(np.abs(stack - median), axis=0)
    level = median - black
    return spread <= np.maximum(STILL_SIGMAS * noise.sigma(level, full_scale), STILL_FRACTION * level)


def detect(residual: np.ndarray, allowed: np.ndarray, noise: float, level: np.ndarray) -> np.ndarray:
    """Glints (G, 3): sub-pixel (col, row) and flux, of ``residual`` (h, w) (lab static image minus the model's
    without spheres) inside the ``allowed`` mask: maxima over the flux square of its white top-hat (small bright
    specks, not the smooth or edge-like leftovers of an imperfect model; one glint per square, as its flux is
    summed there) above DETECT_SIGMAS ``noise``, above DETECT_SIGMAS robust spreads of the top-hat itself, and
    above CONTRAST of the face's ``level`` (h, w, above black) there. The top-hat is taken of the residual's
    bright part: next to a dark leftover (the model brighter than the lab) it would raise a ridge that pulls the
    glint."""
    res = residual.astype(np.float32)
    speck = cv2.morphologyEx(np.maximum(res, 0.0), cv2.MORPH_TOPHAT, np.ones((5, 5), np.uint8))
    spread = 1.4826 * float(np.median(np.abs(speck[allowed] - np.median(speck[allowed])))) if allowed.any() else 0.0
    square = np.ones((2 * FLUX_HALF_PX + 1,) * 2, np.uint8)
    peak = (
        (speck == cv2.dilate(speck, square))
        & allowed
        & (speck > DETECT_SIGMAS * max(noise, spread))
        & (speck > CONTRAST * np.maximum(level, 0.0))
    )
    out, taken = [], []
    h, w = res.shape
    rows, cols = np.nonzero(peak)
    for row, col in zip(rows, cols):  # raster order: of equal maxima in one square, the first is the glint
        if any(abs(row - r) <= FLUX_HALF_PX and abs(col - c) <= FLUX_HALF_PX for r, c in taken):
            continue
        taken.append((row, col))
        r0, r1 = max(0, row - FLUX_HALF_PX), min(h, row + FLUX_HALF_PX + 1)
        c0, c1 = max(0, col - FLUX_HALF_PX), min(w, col + FLUX_HALF_PX + 1)
        patch = np.maximum(speck[r0:r1, c0:c1], 0.0)
        total = float(patch.sum())
        rows, cols = np.mgrid[r0:r1, c0:c1]
        out.append(
            ((cols * patch).sum() / total, (rows * patch).sum() / total, float(np.maximum(res[r0:r1, c0:c1], 0).sum()))
        )
    return np.array(out, dtype=np.float64).reshape(-1, 3)


def place(scene: Scene, glints: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Sphere centres (G, 3) on the face (z = 0) whose glints of ``radii`` (G,) appear at ``glints`` (col, row)."""
    light = direction(scene.light.azimuth_deg, scene.light.elevation_deg)
    centres = []
    for (col, row), rho in zip(glints[:, :2], radii):
        origin, d = pixel_ray(scene, col, row)
        h = light - d
        h /= np.linalg.norm(h)
        t = (rho * h[2] - origin[2]) / d[2]
        centres.append(origin + t * d - rho * h)
    return np.array(centres).reshape(-1, 3)


def with_spheres(scene: Scene, spheres: np.ndarray) -> Scene:
    """``scene`` with its artifacts listed explicitly as ``spheres`` (K, 4) x, y, z, radius."""
    data = scene.as_dict()
    data["artifacts"]["spheres"] = [dict(zip(("x", "y", "z", "radius"), map(float, s))) for s in spheres]
    data["artifacts"]["material"] = scene.sphere_material.model_dump()
    return Scene.from_dict(data)


def square_flux(image: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Sums (G,) of ``image`` (h, w) over the FLUX_HALF_PX square round each point ``at`` (G, 2: col, row), the part
    inside the image (0 where none is)."""
    k = FLUX_HALF_PX
    squares = (
        image[max(0, row - k) : row + k + 1, max(0, col - k) : col + k + 1] for col, row in np.rint(at).astype(int)
    )
    return np.array([float(square.sum()) for square in squares])


def glint_flux(scene: Scene, spheres: np.ndarray, at: np.ndarray, supersample: int = 3) -> np.ndarray:
    """Flux (G,) over the FLUX_HALF_PX square around each point ``at`` (G, 2) of a render of ``scene`` with
    ``spheres`` minus one without them (the fluid at rest)."""
    frames = [
        Renderer(with_spheres(scene, s), supersample=supersample).render(np.zeros((1, 4)))[0]
        for s in (spheres, np.zeros((0, 4)))
    ]
    return np.maximum(square_flux(frames[0] - frames[1], at), 1e-9)


def recover(scene: Scene, residual: np.ndarray, allowed: np.ndarray, noise: float, level: np.ndarray) -> np.ndarray:
    """The artifact spheres (G, 4) whose glints explain ``residual`` (fractions of full scale, the PSF keeps a
    glint's flux; ``level``: the face's brightness in the model, the fluid left out): placed with
    START_RADIUS_MM, resized from their flux against a render, placed again."""
    glints = detect(residual, allowed, noise, level)
    if not len(glints):
        return np.zeros((0, 4))
    radii = np.full(len(glints), START_RADIUS_MM)
    spheres = np.column_stack([place(scene, glints, radii), radii])
    model = glint_flux(scene, spheres, glints[:, :2])
    radii = np.clip(START_RADIUS_MM * np.sqrt(glints[:, 2] / model), 0.002, 0.05)
    return np.column_stack([place(scene, glints, radii), radii])


def glint_positions(scene: Scene, spheres: np.ndarray) -> np.ndarray:
    """Image points (G, 2) of the glints of ``spheres`` (G, 4) in ``scene``'s camera (for scoring)."""
    light = direction(scene.light.azimuth_deg, scene.light.elevation_deg)
    location, _, _ = camera_frame(scene)
    view = location - spheres[:, :3]
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    h = view + light
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    col, row = project(scene, spheres[:, :3] + spheres[:, 3:4] * h)
    return np.column_stack([col, row])
