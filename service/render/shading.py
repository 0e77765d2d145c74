"""Light and materials of scene.md: a sun of finite angular size, GGX specular metal, Lambert nozzle.

Shading model (radiance towards the viewer, per unit sun strength E, the irradiance on a
surface facing the sun, as Cycles defines a sun's strength):

- GGX / Trowbridge-Reitz microfacet reflection (Walter et al. 2007) with the separable
  Smith masking term that Cycles 3.x uses and no Fresnel term (Cycles' Glossy BSDF):
  ``f = F D(h) G1(l) G1(v) / (4 (n.l) (n.v))`` with
  ``D(h) = alpha^2 / (pi ((n.h)^2 (alpha^2 - 1) + 1)^2)`` and
  ``G1(x) = 2 / (1 + sqrt(1 + alpha^2 tan^2 x))``; so a sun direction l contributes
  ``L = E F D(h) G1(l) G1(v) / (4 n.v)`` (its cosine cancels the BRDF's).
- The sun's disc (angular diameter ``angle_deg``) is integrated by a fixed quadrature:
  equal-weight directions on a Vogel spiral over the disc (:func:`sun_directions`).
- Lambert diffuse: ``L = albedo E max(0, n.l) / pi``.
- A small specular sphere of radius rho under the sun reflects it with the radiant intensity
  of a mirror ball, ``I = F E rho^2 / 4`` in every direction (exact for a mirror, the mean
  for a rough one), which makes each artifact sphere a point light for the fluid.
"""

from __future__ import annotations

import math

import numpy as np

from service.scene import Scene, direction

#: Golden angle (radians): successive Vogel-spiral points turn by it.
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def sun_directions(scene: Scene, samples: int) -> np.ndarray:
    """Shape (samples, 3): unit vectors towards equal-area points of the sun's disc.

    One sample is the disc's centre; more spread over the cone of half-angle ``angle_deg / 2``
    on a Vogel spiral (uniform in solid angle), each standing for an equal share of the sun.
    """
    light = scene.light
    centre = direction(light.azimuth_deg, light.elevation_deg)
    radius = math.radians(light.angle_deg) / 2
    if samples == 1 or radius == 0:
        return np.repeat(centre[None], samples, axis=0)
    k = np.arange(samples)
    # equal solid angle: 1 - cos(theta) uniform in [0, 1 - cos(radius)]
    theta = np.arccos(1.0 - (k + 0.5) / samples * (1.0 - math.cos(radius)))
    phi = k * GOLDEN_ANGLE
    helper = np.array([1.0, 0.0, 0.0]) if abs(centre[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(centre, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(centre, e1)
    return np.cos(theta)[:, None] * centre + np.sin(theta)[:, None] * (
        np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    )


def ggx_ndf(cos_h: np.ndarray, alpha: float) -> np.ndarray:
    """GGX normal distribution D for the cosine between normal and half-vector (0 for cos_h <= 0)."""
    a2 = alpha * alpha
    c2 = cos_h * cos_h
    denom = c2 * (a2 - 1.0) + 1.0
    return np.where(cos_h > 0, a2 / (np.pi * denom * denom), 0.0)


def smith_g1(cos: np.ndarray, alpha: float) -> np.ndarray:
    """Smith masking G1 of GGX for the cosine between normal and a direction (0 for cos <= 0)."""
    c2 = np.clip(cos * cos, 1e-12, 1.0)
    tan2 = (1.0 - c2) / c2
    return np.where(cos > 0, 2.0 / (1.0 + np.sqrt(1.0 + alpha * alpha * tan2)), 0.0)


def specular_sun(
    normal: np.ndarray,
    view: np.ndarray,
    suns: np.ndarray,
    visible: np.ndarray | float,
    alpha: float,
    reflectance: float,
    strength: float,
) -> np.ndarray:
    """Radiance of GGX metal lit by the sun: mean over the disc's directions.

    ``normal``, ``view``: shape (..., 3) unit vectors (view points to the viewer);
    ``suns``: shape (J, 3); ``visible``: shape (..., J) or scalar, 1 where that part of the
    sun is unoccluded. Returns shape (...,).
    """
    n_v = np.einsum("...i,...i->...", normal, view)
    n_l = normal @ suns.T  # (..., J)
    half = view[..., None, :] + suns  # (..., J, 3)
    half_norm = np.linalg.norm(half, axis=-1)
    n_h = np.einsum("...i,...ji->...j", normal, half) / np.maximum(half_norm, 1e-12)
    g_v = smith_g1(n_v, alpha)
    lobe = ggx_ndf(n_h, alpha) * smith_g1(n_l, alpha) * visible  # (..., J)
    return np.where(n_v > 0, strength * reflectance * g_v * lobe.mean(axis=-1) / (4.0 * np.maximum(n_v, 1e-6)), 0.0)


def lambert_sun(
    normal: np.ndarray, suns: np.ndarray, visible: np.ndarray | float, albedo: float, strength: float
) -> np.ndarray:
    """Radiance of a Lambert surface lit by the sun: albedo E mean_j(max(0, n.l_j) visible_j) / pi."""
    cos = np.maximum(normal @ suns.T, 0.0) * visible  # (..., J)
    return albedo * strength * cos.mean(axis=-1) / np.pi


def mirror_ball_intensity(radius: np.ndarray, reflectance: float, strength: float) -> np.ndarray:
    """Radiant intensity (per steradian) a specular sphere of ``radius`` reflects of the sun: F E rho^2 / 4."""
    return reflectance * strength * np.asarray(radius) ** 2 / 4.0
