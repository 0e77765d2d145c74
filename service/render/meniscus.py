"""The meniscus of Eq. 1 as a height field, and where rays first meet it.

Along a ray ``x(s) = o + s d`` the squared normalised radius ``u = r^2 / R^2 = A s^2 + B s + C``
is quadratic in ``s``, and Eq. 1 depends on ``u`` alone (J0 is even):

    D(u) = d + p R (1 - u) + a J0(l1 sqrt(u)) + b J0(l2 sqrt(u))           (Eq. 1)

so the ray meets the surface ``z = -D`` where ``F(s) = z(s) + D(u(s)) = 0`` (``F < 0`` in the
air below the metal). Per frame, ``D`` is tabulated at :data:`TABLE_SIZE` nodes of ``u`` (:class:`Profiles`) and
interpolated linearly (error under 1e-6 mm at the default ranges); the roots found are those
of that interpolant. :mod:`service.render.kernel` runs the search below per ray. Outside the bore (``u > 1``) ``u`` is clamped to 1, which keeps
``F`` continuous; only roots inside the bore's cylinder count.

Robustness, with no missed or false hits at grazing angles:

- bracket: a linear interpolant takes its extremes at nodes, so the frame's slab
  ``[-max D, -min D]`` holds every root; ``F <= 0`` where the ray's line enters it and
  ``F >= 0`` where it leaves;
- monotone rays: with ``S`` a bound on the interpolant's ``|dD/dr|`` and ``d_h``, ``d_z`` the
  ray's horizontal and vertical components, ``|dF/ds| >= |d_z| - S |d_h| > 0`` when
  ``S |d_h| < |d_z|``: one root, found by Newton's method safeguarded by bisection, started
  from the root of the chord surface through the centre and rim heights (closed form);
- the others (steep frames, grazing rays): Lipschitz marching, steps of ``|F| / L`` with
  ``L = |d_z| + S |d_h| >= |dF/ds|``, which cannot step over a root, to the first sign
  change, then the same safeguarded Newton. A pair of roots closer than
  :data:`MARCH_MIN_STEP_MM` along the ray (a sliver far below a pixel) may be stepped over.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.special import j0, j1

from service.physics import L1, L2

#: Nodes of the per-frame profile tables over u = r^2 / R^2 in [0, 1]: linear interpolation
#: errs by at most h^2 / 8 max|D''(u)|, 2e-7 mm at the default ranges (a pixel spans ~0.01 mm).
TABLE_SIZE = 513
#: Newton converges when a step is below this (mm along the ray; a pixel spans ~0.01 mm).
TOLERANCE_MM = 1e-5
#: Smallest step of the Lipschitz march (mm along the ray).
MARCH_MIN_STEP_MM = 1e-4
#: Monotone when S |d_h| < MONOTONE_MARGIN |d_z|: keeps |dF/ds| well away from 0.
MONOTONE_MARGIN = 0.98


@lru_cache(maxsize=4)
def mode_tables(size: int = TABLE_SIZE) -> tuple[np.ndarray, ...]:
    """J0(l sqrt(u)) of both modes and their u-derivatives at ``size`` nodes: 4 arrays (size,).

    d/du J0(l sqrt u) = -l^2 J1(x) / (2 x) with x = l sqrt u, which tends to -l^2 / 4 at u = 0.
    """
    u = np.linspace(0.0, 1.0, size)
    out = []
    for l in (L1, L2):
        x = l * np.sqrt(u)
        safe = np.where(x > 0, x, 1.0)
        out.append((j0(x), np.where(x > 0, -l * l * j1(safe) / (2 * safe), -l * l / 4)))
    return out[0][0], out[1][0], out[0][1], out[1][1]


@dataclass(frozen=True)
class Profiles:
    """Eq. 1 tabulated over u for F frames: arrays (F, T), float64.

    ``value`` / ``step``: D at the nodes (mm) and the difference to the next node (0 at the last);
    ``slope`` / ``slope_step``: the smooth dD/du at the nodes, for shading normals;
    ``z_low``, ``z_high`` (F,): the slab of surface heights z = -D; ``max_slope`` (F,): a bound
    on |dD/dr| of the interpolant; ``convex`` (F,): the metal ``z > -D`` is convex (D concave
    in x, y: dD/du <= 0 and dD/du + 2 u d2D/du2 <= 0 at every node), so no ray leaving the
    surface into the air can meet it again and the renderer skips the search for a second bounce.
    """

    value: np.ndarray
    step: np.ndarray
    slope: np.ndarray
    slope_step: np.ndarray
    z_low: np.ndarray
    z_high: np.ndarray
    max_slope: np.ndarray
    convex: np.ndarray

    @classmethod
    def build(cls, coeffs: np.ndarray, radius: float, size: int = TABLE_SIZE) -> Profiles:
        """Tables for coefficients (F, 4): d, p, a, b (Eq. 1)."""
        m1, m2, m1_du, m2_du = mode_tables(size)
        u = np.linspace(0.0, 1.0, size)
        d, p, a, b = (coeffs[:, i, None] for i in range(4))  # (F, 1)
        value = d + p * radius * (1.0 - u) + a * m1 + b * m2  # (F, T)
        slope = -p * radius + a * m1_du + b * m2_du  # (F, T) dD/du
        step = np.diff(value, axis=1, append=value[:, -1:])
        slope_step = np.diff(slope, axis=1, append=slope[:, -1:])
        # |dD/dr| = |dD/du| 2 sqrt(u) / R, bounded per cell by its far node's sqrt(u)
        per_cell = np.abs(step[:, :-1]) * (size - 1) * 2.0 * np.sqrt(u[1:]) / radius
        curvature = slope + 2.0 * u * slope_step * (size - 1)  # R^2 / 2 d2D/dr2
        convex = (slope.max(axis=1) <= 0.0) & (curvature[:, :-1].max(axis=1) <= 0.0)
        return cls(
            value=value,
            step=step,
            slope=slope,
            slope_step=slope_step,
            z_low=-value.max(axis=1),
            z_high=-value.min(axis=1),
            max_slope=per_cell.max(axis=1),
            convex=convex,
        )


def ray_terms(origin: np.ndarray, direction: np.ndarray, radius: float) -> np.ndarray:
    """Shape (M, 6): A, B, C, oz, dz, dh of rays (M, 3), with u(s) = A s^2 + B s + C, z(s) = oz + s dz
    and dh the horizontal length of the direction."""
    dh2 = direction[:, 0] ** 2 + direction[:, 1] ** 2
    r2 = radius * radius
    return np.stack(
        [
            dh2 / r2,
            2 * (origin[:, 0] * direction[:, 0] + origin[:, 1] * direction[:, 1]) / r2,
            (origin[:, 0] ** 2 + origin[:, 1] ** 2) / r2,
            origin[:, 2],
            direction[:, 2],
            np.sqrt(dh2),
        ],
        axis=1,
    )
