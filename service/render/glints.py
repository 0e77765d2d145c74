"""The artifact spheres' sun glints seen directly: point sources added to the pixel that holds each.

A defect's glint is the sun's image in a sphere 6-18 um across, a spot far smaller than a pixel: rays traced through
the pixel find it or miss it, so a traced glint's brightness is the rays' luck at any count per pixel (and Blender
Cycles' at its samples). A specular sphere reflects the sun as a point source of intensity F E r^2 / 4
(:func:`service.render.shading.mirror_ball_intensity`, which the fluid's reflections of the spheres use too), so its
pixel receives that intensity over the distance squared, whatever the rays: here it is added to the static frame in
the pixel holding the glint (a box pixel filter: a camera's pixel integrates its whole area), where the camera sees
it and the sun lights it (docs/calibration.md, "H's defects, one by one").
"""

from __future__ import annotations

import numpy as np

from service.render import nozzle
from service.render.camera import camera_frame, focal_px, project
from service.render.shading import mirror_ball_intensity
from service.scene import Scene

#: How far (mm) the first static hit along the camera's ray to a glint may lie from it and still be the glint itself.
SEEN_MM = 1e-6


def splats(scene: Scene, suns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (G,) (flat index in the ROI) and radiance (G,) each visible glint adds to its pixel's mean, for the
    sun's directions ``suns`` (J, 3): its share of them that reach the glint's point unblocked lights it."""
    spheres = scene.spheres
    cam = scene.camera
    if not len(spheres):
        return np.zeros(0, np.int64), np.zeros(0)
    location, forward, _ = camera_frame(scene)
    centre, radius = spheres[:, :3], spheres[:, 3]
    sun = suns.mean(axis=0)
    sun /= np.linalg.norm(sun)
    view = location - centre
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    half = view + sun
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    point = centre + radius[:, None] * half  # where the sphere's normal is the half-vector
    towards = point - location
    distance = np.linalg.norm(towards, axis=1)
    towards /= distance[:, None]
    hits = nozzle.trace(scene, np.broadcast_to(location, point.shape).copy(), towards, np.zeros(len(point)))
    seen = (hits.sphere == np.arange(len(point))) & (np.abs(hits.t - distance) <= SEEN_MM)
    lit = nozzle.sun_visibility(scene, point, half, suns).mean(axis=1)
    col, row = project(scene, point)
    col, row = np.rint(col).astype(np.int64), np.rint(row).astype(np.int64)
    inside = seen & (lit > 0) & (col >= 0) & (col < cam.width_px) & (row >= 0) & (row < cam.height_px)
    # a point source's irradiance at the camera over the pixel's solid angle: the radiance of a pixel it would fill
    cosine = towards @ forward
    pixel_solid_angle = cosine**3 / focal_px(scene) ** 2
    intensity = mirror_ball_intensity(radius, scene.sphere_material.reflectance, scene.light.strength)
    radiance = lit * intensity / distance**2 / pixel_solid_angle
    return (row * cam.width_px + col)[inside], radiance[inside]
