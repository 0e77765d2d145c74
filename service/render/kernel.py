"""The per-frame work of the ray tracer, compiled: fluid hits and their shading for a batch of frames.

One pass per (frame, ray that can meet the fluid), frames in parallel. The method is the one
:mod:`service.render.meniscus` describes (bracket from the frame's slab; safeguarded Newton on
monotone rays, Lipschitz marching on the others) and the shading that
:mod:`service.render.shading` defines; this module only runs it per ray, so that each ray
stops as soon as it is done instead of waiting for the slowest one of an array.

Why compiled (numba): the root finding is iterative and branchy per ray; evaluated
array-at-a-time with numpy it needs gathers, compaction and temporaries, and ran some ten
times slower than this kernel on the same frames (``meniscope bench render`` measures it).
"""

from __future__ import annotations

import math
import threading

import numpy as np
from numba import njit, prange

from service.render.meniscus import MARCH_MIN_STEP_MM, MONOTONE_MARGIN, TOLERANCE_MM

#: Newton / bisection steps at most: bisection alone reaches float64 resolution from any slab.
MAX_ITERATIONS = 64
#: Where along the mirror ray the search for a second fluid hit starts (mm): past the first hit's
#: root tolerance, far below a pixel (~0.01 mm).
SECOND_BOUNCE_START_MM = 1e-4
#: Sphere-cull table entries are angles in units of this (radians), rounded down.
REACH_UNIT = 1e-3

#: Relaxed floating point (fused multiply-add, reciprocals, fast math functions) but no
#: assumption that values are finite: the march reports "no root" as NaN.
FASTMATH = {"contract", "arcp", "afn", "reassoc", "nsz"}

#: numba's default thread pool may not be entered by two Python threads at once.
LAUNCH = threading.Lock()


@njit(cache=True, inline="always", error_model="numpy", fastmath=FASTMATH)
def _gap(s, f, A, B, C, oz, dz, value, step):  # pragma: no cover - compiled
    """F(s) = z + D(u(s)) of the piecewise-linear profile of frame f, and dF/ds."""
    size = value.shape[1]
    u = (A * s + B) * s + C
    if u >= 1.0:  # outside the bore: D clamped to the rim's, d
        return oz + s * dz + value[f, size - 1], dz
    x = max(u, 0.0) * (size - 1)
    i = min(int(x), size - 2)
    w = x - i
    return oz + s * dz + value[f, i] + w * step[f, i], dz + step[f, i] * (size - 1) * (2.0 * A * s + B)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FASTMATH)
def _newton(s, neg, pos, f, A, B, C, oz, dz, value, step):  # pragma: no cover - compiled
    """Root of F in the bracket F(neg) <= 0 <= F(pos): Newton steps, bisection where they leave it."""
    for _ in range(MAX_ITERATIONS):
        g, dg = _gap(s, f, A, B, C, oz, dz, value, step)
        if g == 0.0:
            return s
        if g < 0.0:
            neg = s
        else:
            pos = s
        lo, hi = min(neg, pos), max(neg, pos)
        nxt = s - g / dg if dg != 0.0 else lo - 1.0
        if lo - TOLERANCE_MM <= nxt <= hi + TOLERANCE_MM:
            done = abs(nxt - s) <= TOLERANCE_MM
            s = min(max(nxt, lo), hi)
        else:
            s = 0.5 * (lo + hi)
            done = False
        if done or hi - lo <= TOLERANCE_MM:
            return s
    return s


@njit(cache=True, inline="always", error_model="numpy", fastmath=FASTMATH)
def _march(enter, leave, lipschitz, f, A, B, C, oz, dz, value, step):  # pragma: no cover - compiled
    """First root of F in [enter, leave] by Lipschitz steps; NaN when there is none."""
    s = enter
    g, _ = _gap(s, f, A, B, C, oz, dz, value, step)
    if g == 0.0:
        return s
    while s < leave:
        nxt = min(s + max(abs(g) / lipschitz, MARCH_MIN_STEP_MM), leave)
        gn, _ = _gap(nxt, f, A, B, C, oz, dz, value, step)
        if gn == 0.0:
            return nxt
        if (gn < 0.0) != (g < 0.0):
            if g < 0.0:
                return _newton(0.5 * (s + nxt), s, nxt, f, A, B, C, oz, dz, value, step)
            return _newton(0.5 * (s + nxt), nxt, s, f, A, B, C, oz, dz, value, step)
        s, g = nxt, gn
    return math.nan


@njit(cache=True, inline="always", error_model="numpy", fastmath=FASTMATH)
def _ggx(cos_h, a2):  # pragma: no cover - compiled
    c2 = cos_h * cos_h
    den = c2 * (a2 - 1.0) + 1.0
    return a2 / (math.pi * den * den) if cos_h > 0.0 else 0.0


@njit(cache=True, inline="always", error_model="numpy", fastmath=FASTMATH)
def _smith(cos, a2):  # pragma: no cover - compiled
    if cos <= 0.0:
        return 0.0
    c2 = min(cos * cos, 1.0)
    return 2.0 / (1.0 + math.sqrt(1.0 + a2 * (1.0 - c2) / c2))


@njit(cache=True, inline="always", error_model="numpy", fastmath=FASTMATH)
def _chord(coeffs, f, radius):  # pragma: no cover - compiled
    """The chord surface of frame f through its centre and rim heights: centre depth D(0) and slope over u."""
    d0 = coeffs[f, 0]
    centre = d0 + coeffs[f, 1] * radius + coeffs[f, 2] + coeffs[f, 3]
    return centre, d0 - centre


@njit(cache=True, inline="always", error_model="numpy", fastmath=FASTMATH)
def _first_hit(
    f, A, B, C, oz, dz, dh, enter, leave, zl, zh, slope_f, centre, k_chord, value, step
):  # pragma: no cover - compiled
    """Distance along a ray (A, B, C, oz, dz, dh of :func:`service.render.meniscus.ray_terms`) to its first
    hit of frame f's surface within [enter, leave]; NaN when it has none. ``zl``, ``zh``: the frame's
    slab; ``slope_f``: its slope bound."""
    if dz != 0.0:
        sa, sb = (zl - oz) / dz, (zh - oz) / dz  # F <= 0 at sa, >= 0 at sb
        e, l = max(min(sa, sb), enter), min(max(sa, sb), leave)
    elif zl <= oz <= zh:
        sa = sb = 0.0
        e, l = enter, leave
    else:
        return math.nan
    if e > l:  # e == l: a flat frame's slab is one plane
        return math.nan
    if dz != 0.0 and slope_f * dh < MONOTONE_MARGIN * abs(dz):
        # one root: Newton from the chord surface's root, kept in the slab's bracket
        q2, q1, q0 = k_chord * A, dz + k_chord * B, oz + centre + k_chord * C
        disc = max(q1 * q1 - 4.0 * q2 * q0, 0.0)
        den = -q1 - math.copysign(math.sqrt(disc), q1)
        if den != 0.0:
            s0 = 2.0 * q0 / den
        elif q1 != 0.0:
            s0 = -q0 / q1
        else:
            s0 = 0.5 * (sa + sb)
        s0 = min(max(s0, min(sa, sb)), max(sa, sb))
        s = _newton(s0, sa, sb, f, A, B, C, oz, dz, value, step)
        return s if e <= s <= l else math.nan
    return _march(e, l, abs(dz) + slope_f * dh, f, A, B, C, oz, dz, value, step)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FASTMATH)
def _normal(f, px, py, slope, slope_step, r2):  # pragma: no cover - compiled
    """Unit normal, facing the air below, of frame f's surface z = -D at (px, py): from the smooth dD/du (Eq. 1)."""
    size = slope.shape[1]
    x = min(max((px * px + py * py) / r2, 0.0), 1.0) * (size - 1)
    i = min(int(x), size - 2)
    g = -2.0 * (slope[f, i] + (x - i) * slope_step[f, i]) / r2
    inv = 1.0 / math.sqrt(g * g * (px * px + py * py) + 1.0)
    return g * px * inv, g * py * inv, -inv


@njit(cache=True, inline="always", error_model="numpy", fastmath=FASTMATH)
def _sun(
    px, py, pz, nx, ny, nz, vx, vy, vz, n_v, g_v, suns, a2, r2, ro2, strength, reflectance
):  # pragma: no cover - compiled
    """GGX radiance towards v of the fluid at p (normal n) lit by the sun's disc (``shading.specular_sun``),
    each part of the disc seen through the outlet when p is inside the bore."""
    n_suns = suns.shape[0]
    lit = 0.0
    for j in range(n_suns):
        lx, ly, lz = suns[j, 0], suns[j, 1], suns[j, 2]
        if lz != 0.0:
            t0 = -pz / lz
            cx, cy = px + t0 * lx, py + t0 * ly
            c2 = cx * cx + cy * cy
            visible = (lz < 0.0 and c2 < r2) if pz > 0.0 else (lz < 0.0 or c2 > ro2)
        else:
            visible = pz <= 0.0
        if not visible:
            continue
        n_l = nx * lx + ny * ly + nz * lz
        hx, hy, hz = vx + lx, vy + ly, vz + lz
        n_h = (nx * hx + ny * hy + nz * hz) / max(math.sqrt(hx * hx + hy * hy + hz * hz), 1e-12)
        lit += _ggx(n_h, a2) * _smith(n_l, a2)
    return strength * reflectance * g_v * lit / (n_suns * 4.0 * n_v)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FASTMATH)
def _second_hit(
    f, px, py, pz, rx, ry, rz, zl, zh, slope_f, centre, k_chord, value, step, r2
):  # pragma: no cover - compiled
    """Distance along the mirror ray from the surface point p to where it meets the fluid again (NaN: never),
    within the bore's cylinder. A ray the slope bound makes monotone meets the surface once, at p itself."""
    A, dh = (rx * rx + ry * ry) / r2, math.sqrt(rx * rx + ry * ry)
    if slope_f * dh < MONOTONE_MARGIN * abs(rz):
        return math.nan
    B, C = 2.0 * (px * rx + py * ry) / r2, (px * px + py * py) / r2
    leave = (-B + math.sqrt(max(B * B - 4.0 * A * (C - 1.0), 0.0))) / (2.0 * A) if A > 0.0 else 1e3
    g, _ = _gap(SECOND_BOUNCE_START_MM, f, A, B, C, pz, rz, value, step)
    if g >= 0.0 or leave <= SECOND_BOUNCE_START_MM:  # grazing: the ray does not clear the surface
        return math.nan
    return _first_hit(
        f, A, B, C, pz, rz, dh, SECOND_BOUNCE_START_MM, leave, zl, zh, slope_f, centre, k_chord, value, step
    )


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FASTMATH)
def first_hits(
    coeffs, value, step, z_low, z_high, max_slope, terms, enter, leave, radius, out
):  # pragma: no cover - compiled
    """Distances (F, M) along each candidate ray to its first hit of each frame's surface (NaN: none), into ``out``."""
    for f in prange(out.shape[0]):
        centre, k_chord = _chord(coeffs, f, radius)
        for m in range(out.shape[1]):
            out[f, m] = _first_hit(
                f,
                terms[m, 0],
                terms[m, 1],
                terms[m, 2],
                terms[m, 3],
                terms[m, 4],
                terms[m, 5],
                enter[m],
                leave[m],
                z_low[f],
                z_high[f],
                max_slope[f],
                centre,
                k_chord,
                value,
                step,
            )


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FASTMATH)
def trace(
    coeffs,
    value,
    step,
    slope,
    slope_step,
    z_low,
    z_high,
    max_slope,
    convex,
    ray_o,
    ray_d,
    terms,
    enter,
    leave,
    static,
    slot,
    inv_samples,
    touched,
    static_touched,
    exposure,
    suns,
    sun_stride,
    alpha,
    reflectance,
    strength,
    radius,
    outer_radius,
    bore_depth,
    spheres,
    intensity,
    reach,
    reach_start,
    reach_scale,
    min_cos_view,
    only,
    out,
):  # pragma: no cover - compiled
    """Write the pixels the fluid can touch into the frames ``out`` (F, H W) (float32, holding the static
    image already): their static radiance ``static_touched`` (P,) at pixels ``touched`` (P,), plus the
    fluid's radiance less the static radiance it hides, times ``exposure``, clipped to [0, 1].

    Per frame f (tables of :class:`service.render.meniscus.Profiles` as (F, T) arrays) and
    candidate ray m (origin ``ray_o`` (M, 3), direction ``ray_d`` (M, 3), ``terms`` (M, 6):
    A, B, C, oz, dz, dh; bore interval ``enter``/``leave`` (M,); ``static`` radiance (M,);
    ``slot`` (M,): its pixel's index in ``touched``), a hit adds ``(L - static) * inv_samples`` to that pixel. ``suns`` (J, 3),
    of which ray m shades with every ``sun_stride``-th from the (m mod ``sun_stride``)-th (the rays of a pixel share
    the disc between them);
    ``spheres`` (K, 4) with ``intensity`` (K,); ``reach`` (M, I, K) int16 in REACH_UNIT. ``only`` (F, P) bool: per
    frame, the touched pixels to trace and write, the others left as ``out`` holds them; (0, 0): every one.
    """
    n_frames, n_rays = out.shape[0], terms.shape[0]
    a2 = alpha * alpha
    n_suns, n_spheres, n_int = suns.shape[0], spheres.shape[0], reach.shape[1]
    r2, ro2 = radius * radius, outer_radius * outer_radius
    sun_x = sun_y = sun_z = 0.0  # the disc's mean direction: where sphere glints face
    for j in range(n_suns):
        sun_x += suns[j, 0]
        sun_y += suns[j, 1]
        sun_z += suns[j, 2]
    for f in prange(n_frames):
        frame = np.empty(static_touched.shape[0])
        frame[:] = static_touched
        zl, zh, slope_f = z_low[f], z_high[f], max_slope[f]
        centre, k_chord = _chord(coeffs, f, radius)
        chosen = only.shape[0] > 0
        for m in range(n_rays):
            if chosen and not only[f, slot[m]]:
                continue
            s = _first_hit(
                f,
                terms[m, 0],
                terms[m, 1],
                terms[m, 2],
                terms[m, 3],
                terms[m, 4],
                terms[m, 5],
                enter[m],
                leave[m],
                zl,
                zh,
                slope_f,
                centre,
                k_chord,
                value,
                step,
            )
            if math.isnan(s):
                continue
            own = suns[m % sun_stride :: sun_stride]
            # ---- the hit: normal from the smooth dD/du (Eq. 1), view towards the camera ----
            px, py, pz = ray_o[m, 0] + s * ray_d[m, 0], ray_o[m, 1] + s * ray_d[m, 1], ray_o[m, 2] + s * ray_d[m, 2]
            nx, ny, nz = _normal(f, px, py, slope, slope_step, r2)
            vx, vy, vz = -ray_d[m, 0], -ray_d[m, 1], -ray_d[m, 2]
            n_v = nx * vx + ny * vy + nz * vz
            radiance = 0.0
            if n_v > 0.0:
                g_v = _smith(n_v, a2)
                # the mirror direction: where the GGX lobe points; on a concave surface it may meet the fluid
                # again, which then hides the sun there and shows the sun's reflection at that second point
                rx, ry, rz = 2.0 * n_v * nx - vx, 2.0 * n_v * ny - vy, 2.0 * n_v * nz - vz
                q = (
                    math.nan
                    if convex[f]
                    else _second_hit(f, px, py, pz, rx, ry, rz, zl, zh, slope_f, centre, k_chord, value, step, r2)
                )
                if math.isnan(q):
                    radiance = _sun(
                        px, py, pz, nx, ny, nz, vx, vy, vz, n_v, g_v, own, a2, r2, ro2, strength, reflectance
                    )
                else:
                    qx, qy, qz = px + q * rx, py + q * ry, pz + q * rz
                    mx, my, mz = _normal(f, qx, qy, slope, slope_step, r2)
                    m_v = -(mx * rx + my * ry + mz * rz)
                    if m_v > 0.0:
                        radiance = reflectance * _sun(
                            qx,
                            qy,
                            qz,
                            mx,
                            my,
                            mz,
                            -rx,
                            -ry,
                            -rz,
                            m_v,
                            _smith(m_v, a2),
                            own,
                            a2,
                            r2,
                            ro2,
                            strength,
                            reflectance,
                        )
                # the spheres' reflections of the sun: point lights, culled by the reach table
                if n_spheres:
                    tilt = math.acos(min(max(-nz, -1.0), 1.0))
                    k_int = int((s - reach_start[m]) * reach_scale[m])
                    check_all = k_int < 0 or k_int >= n_int or n_v < min_cos_view
                    k_int = min(max(k_int, 0), n_int - 1)
                    for k in range(n_spheres):
                        if not check_all and reach[m, k_int, k] * REACH_UNIT > tilt:
                            continue
                        wx, wy, wz = spheres[k, 0] - px, spheres[k, 1] - py, spheres[k, 2] - pz
                        dist = math.sqrt(wx * wx + wy * wy + wz * wz)
                        if dist <= 0.0:
                            continue
                        wx, wy, wz = wx / dist, wy / dist, wz / dist
                        # the glint faces the sun and the fluid point; hidden inside the nozzle body
                        gx, gy, gz = sun_x / n_suns - wx, sun_y / n_suns - wy, sun_z / n_suns - wz
                        gn = math.sqrt(gx * gx + gy * gy + gz * gz)
                        if gn <= 0.0:
                            continue
                        rad = spheres[k, 3]
                        gx, gy, gz = (
                            spheres[k, 0] + rad * gx / gn,
                            spheres[k, 1] + rad * gy / gn,
                            spheres[k, 2] + rad * gz / gn,
                        )
                        g2 = gx * gx + gy * gy
                        if 0.0 < gz <= bore_depth and r2 <= g2 <= ro2:
                            continue
                        if (pz > 0.0) != (gz > 0.0):  # the path crosses the outlet plane: through the outlet only
                            t0 = pz / (pz - gz)
                            cx, cy = px + t0 * (gx - px), py + t0 * (gy - py)
                            if cx * cx + cy * cy >= r2:
                                continue
                        n_w = nx * wx + ny * wy + nz * wz
                        hx, hy, hz = vx + wx, vy + wy, vz + wz
                        n_h = (nx * hx + ny * hy + nz * hz) / max(math.sqrt(hx * hx + hy * hy + hz * hz), 1e-12)
                        spread = max(dist, 2.0 * rad)
                        radiance += (
                            reflectance
                            * _ggx(n_h, a2)
                            * _smith(n_w, a2)
                            * g_v
                            / (4.0 * n_v)
                            * intensity[k]
                            / (spread * spread)
                        )
            frame[slot[m]] += (radiance - static[m]) * inv_samples
        for q in range(frame.shape[0]):
            if not chosen or only[f, q]:
                out[f, touched[q]] = min(max(exposure * frame[q], 0.0), 1.0)
