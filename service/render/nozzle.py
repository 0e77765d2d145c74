"""The static part of the scene: nozzle body and artifact spheres, traced and shaded once per renderer.

Geometry (scene.md, "World frame", "Materials"): the nozzle body is the solid
``R <= r <= outer_radius, 0 <= z <= bore_depth`` (bottom face, bore wall, outer wall, top),
Lambert with ``albedo``; the bore above the meniscus holds liquid metal, so a ray that
reaches ``z = bore_depth`` inside the bore stops there, black. Artifact spheres are GGX
metal of their own (``scene.sphere_material``). The sun's visibility from a static point is traced against the body
and the spheres; the fluid's shadow on the static scene is not modelled (it would be per
frame and falls on the dark nozzle, under 2 % of full scale).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from enum import IntEnum

import numpy as np

from service.render.shading import lambert_sun
from service.scene import Scene

#: Offset (mm) that moves a shadow ray's origin off its own surface.
SURFACE_EPS = 1e-7
#: Rays per block that :func:`trace` follows at once.
TRACE_CHUNK = 4096


class Hit(IntEnum):
    """What a ray met first."""

    NONE = 0
    FACE = 1  # bottom face z = 0, R <= r <= outer radius
    BORE = 2  # bore wall r = R, inside the nozzle
    OUTER = 3  # outer wall r = outer radius
    TOP = 4  # z = bore depth: the nozzle's top, or the liquid column inside the bore
    SPHERE = 5


@dataclass(frozen=True)
class StaticHits:
    """First hit of P rays: ``t`` (P,) ray parameter (inf where none), ``kind`` (P,) :class:`Hit`,
    ``normal`` (P, 3) outward unit normal, ``sphere`` (P,) index of the sphere hit (-1 otherwise)."""

    t: np.ndarray
    kind: np.ndarray
    normal: np.ndarray
    sphere: np.ndarray


def _roots(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both real roots of a t^2 + b t + c (a > 0), NaN-free: inf where there is none."""
    disc = b * b - 4 * a * c
    ok = (disc >= 0) & (a > 0)
    sq = np.sqrt(np.where(ok, disc, 0.0))
    safe = np.where(ok, 2 * a, 1.0)
    return np.where(ok, (-b - sq) / safe, np.inf), np.where(ok, (-b + sq) / safe, np.inf)


def cylinder_interval(origin: np.ndarray, direction: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Parameters (enter, leave) where rays are inside the infinite cylinder r <= radius; inf, inf if never."""
    a = direction[..., 0] ** 2 + direction[..., 1] ** 2
    b = 2 * (origin[..., 0] * direction[..., 0] + origin[..., 1] * direction[..., 1])
    c = origin[..., 0] ** 2 + origin[..., 1] ** 2 - radius * radius
    return _roots(a, b, c)


def _plane(
    origin: np.ndarray, direction: np.ndarray, z: float, r_lo: float, r_hi: float, t_min: np.ndarray
) -> np.ndarray:
    """Parameter where rays cross the plane ``z`` inside the annulus [r_lo, r_hi] after t_min; inf else."""
    dz = direction[:, 2]
    t = np.where(dz != 0, (z - origin[:, 2]) / np.where(dz != 0, dz, 1.0), np.inf)
    p = origin[:, :2] + np.where(np.isfinite(t), t, 0.0)[:, None] * direction[:, :2]
    r2 = (p * p).sum(axis=1)
    return np.where((t > t_min) & (r2 >= r_lo * r_lo) & (r2 <= r_hi * r_hi), t, np.inf)


def _wall(origin: np.ndarray, direction: np.ndarray, radius: float, z_hi: float, t_min: np.ndarray) -> np.ndarray:
    """Parameter of the first crossing of the cylinder wall r = radius, 0 <= z <= z_hi, after t_min; inf else."""
    best = np.full(origin.shape[0], np.inf)
    for t in cylinder_interval(origin, direction, radius):
        z = origin[:, 2] + np.where(np.isfinite(t), t, 0.0) * direction[:, 2]
        ok = np.isfinite(t) & (t > t_min) & (z >= 0) & (z <= z_hi)
        best = np.where(ok & (t < best), t, best)
    return best


def _spheres(
    origin: np.ndarray, direction: np.ndarray, spheres: np.ndarray, t_min: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest sphere hit after t_min: parameter (P,) (inf if none) and sphere index (P,) (-1 if none)."""
    if spheres.shape[0] == 0:
        return np.full(origin.shape[0], np.inf), np.full(origin.shape[0], -1)
    oc = origin[:, None, :] - spheres[None, :, :3]  # (P, K, 3)
    b = np.einsum("pki,pi->pk", oc, direction)
    c = (oc * oc).sum(axis=2) - spheres[None, :, 3] ** 2
    disc = b * b - c
    sq = np.sqrt(np.maximum(disc, 0.0))
    near, far = -b - sq, -b + sq
    t = np.where(near > t_min[:, None], near, np.where(far > t_min[:, None], far, np.inf))
    t = np.where(disc >= 0, t, np.inf)
    index = np.argmin(t, axis=1)
    best = t[np.arange(t.shape[0]), index]
    return best, np.where(np.isfinite(best), index, -1)


def trace(scene: Scene, origin: np.ndarray, direction: np.ndarray, t_min: np.ndarray) -> StaticHits:
    """First hit of rays (P, 3) with the nozzle body or a sphere, after parameter ``t_min`` (P,)."""
    if origin.shape[0] > TRACE_CHUNK:  # each block's (block, K, 3) work stays in cache; the same bits as one go
        blocks = [slice(i, i + TRACE_CHUNK) for i in range(0, origin.shape[0], TRACE_CHUNK)]
        parts = [trace(scene, origin[at], direction[at], t_min[at]) for at in blocks]
        return StaticHits(*(np.concatenate([getattr(h, f.name) for h in parts]) for f in fields(StaticHits)))
    nz = scene.nozzle
    R, Ro, h = nz.radius_mm, nz.outer_radius_mm, nz.bore_depth_mm
    candidates = {
        Hit.FACE: _plane(origin, direction, 0.0, R, Ro, t_min),
        Hit.BORE: _wall(origin, direction, R, h, t_min),
        Hit.OUTER: _wall(origin, direction, Ro, h, t_min),
        Hit.TOP: _plane(origin, direction, h, 0.0, Ro, t_min),
    }
    t_sphere, sphere = _spheres(origin, direction, scene.spheres, t_min)
    candidates[Hit.SPHERE] = t_sphere
    kinds = np.array(list(candidates))
    ts = np.stack(list(candidates.values()), axis=1)  # (P, 5)
    first = np.argmin(ts, axis=1)
    t = ts[np.arange(ts.shape[0]), first]
    kind = np.where(np.isfinite(t), kinds[first], Hit.NONE)
    point = origin + np.where(np.isfinite(t), t, 0.0)[:, None] * direction
    normal = np.zeros_like(point)
    normal[kind == Hit.FACE] = (0.0, 0.0, -1.0)
    normal[kind == Hit.TOP] = (0.0, 0.0, 1.0)
    radial = np.concatenate([point[:, :2], np.zeros((point.shape[0], 1))], axis=1)
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-12)
    normal[kind == Hit.BORE] = -radial[kind == Hit.BORE]  # the bore wall faces the axis
    normal[kind == Hit.OUTER] = radial[kind == Hit.OUTER]
    on_sphere = kind == Hit.SPHERE
    if on_sphere.any():
        s = scene.spheres[sphere[on_sphere]]
        normal[on_sphere] = (point[on_sphere] - s[:, :3]) / s[:, 3:4]
    return StaticHits(t=t, kind=kind, normal=normal, sphere=np.where(on_sphere, sphere, -1))


def sun_visibility(scene: Scene, point: np.ndarray, normal: np.ndarray, suns: np.ndarray) -> np.ndarray:
    """Shape (P, J): 1.0 where the ray from ``point`` (P, 3) towards sun direction j meets nothing static."""
    p = point.shape[0]
    start = np.repeat(point + SURFACE_EPS * normal, suns.shape[0], axis=0)  # (P J, 3)
    towards = np.tile(suns, (p, 1))
    blocked = trace(scene, start, towards, np.zeros(start.shape[0])).kind != Hit.NONE
    return (~blocked).reshape(p, suns.shape[0]).astype(np.float64)


def shade(scene: Scene, origin: np.ndarray, direction: np.ndarray, hits: StaticHits, suns: np.ndarray) -> np.ndarray:
    """Radiance (P,) of each ray's static hit under the sun (0 where it met nothing or the liquid column, or a
    sphere: its sun glint, a spot far smaller than a pixel that rays find or miss by luck, is a point source added to
    its pixel whole, :mod:`service.render.glints`)."""
    radiance = np.zeros(origin.shape[0])
    point = origin + np.where(np.isfinite(hits.t), hits.t, 0.0)[:, None] * direction
    inside_bore = (point[:, 0] ** 2 + point[:, 1] ** 2) < scene.nozzle.radius_mm**2
    diffuse = np.isin(hits.kind, (Hit.FACE, Hit.BORE, Hit.OUTER, Hit.TOP)) & ~((hits.kind == Hit.TOP) & inside_bore)
    if diffuse.any():
        vis = sun_visibility(scene, point[diffuse], hits.normal[diffuse], suns)
        radiance[diffuse] = lambert_sun(hits.normal[diffuse], suns, vis, scene.nozzle.albedo, scene.light.strength)
    return radiance
