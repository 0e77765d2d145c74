"""The batched ray tracer for the scene class of shared/spec/scene.md: frames from Eq. 1 coefficients.

What a frame holds: the pinhole camera's view of the ROI (:mod:`.camera`), the nozzle body and
artifact spheres lit by the sun (:mod:`.nozzle`, shaded once per renderer: they never move),
and the meniscus of Eq. 1 (:mod:`.meniscus`), GGX metal (:mod:`.shading`) lit by

- the sun, its disc integrated by ``sun_samples`` directions, shadowed by the bore wall when
  the surface sits inside the bore (the bore is convex, so a point sees the sun exactly when
  its ray towards it leaves through the outlet);
- the artifact spheres' reflections of the sun (the second bounce): each sphere is a point
  light of the radiant intensity of a mirror ball at its centre, hidden where its glint
  would lie inside the nozzle body or the path leaves the bore through the wall. Which
  sphere can light which ray at all is decided once from geometry and the frame's largest
  slope, so frames whose surface cannot tilt far enough skip the work.

Per frame only rays that can meet the fluid are traced (:mod:`.kernel`, frames in parallel);
the rest of the image is the static one. Anti-aliasing: ``supersample`` x ``supersample``
stratified rays per pixel, box filter. Output: ``clip(exposure * radiance, 0, 1)`` as float32
(N, H, W), linear (scene.md, "Camera").
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import ArrayLike
from scipy.ndimage import binary_dilation

from service.errors import MeniscopeError
from service.physics import coefficient_array
from service.render import glints, kernel, nozzle
from service.render.camera import pixel_rays
from service.render.meniscus import Profiles, ray_terms
from service.render.shading import mirror_ball_intensity, sun_directions
from service.scene import Scene

#: Sun directions for the static scene (shaded once, so it can afford soft shadows).
STATIC_SUN_SAMPLES = 32
#: Radiance below which a sphere's reflection in the fluid is left out: an eighth of an 8-bit
#: step, and well under what the model already leaves out (the fluid's reflection of the lit
#: nozzle face, ~0.015).
FAINTEST = 5e-4
#: The sphere cull assumes n.v at least this; grazing hits below it consider every sphere.
CULL_MIN_COS_VIEW = 0.25
#: Points along each ray (intervals + 1) at which it is decided which spheres can light it.
CULL_SAMPLES = 33
#: Fluid rays per block of :meth:`Renderer._sphere_reach`'s table.
REACH_CHUNK = 512
#: A pixel stepping by over this (of full scale) to a neighbour holds detail finer than its rays: with
#: ``edge_supersample`` it takes the finer rays' value (the few such pixels hold nearly all that finer rays change:
#: docs/calibration.md). Below it the two values are blended, linearly from ``EDGE_STEP / 2`` (none of the finer):
#: a pixel's value then moves smoothly as a scene's change takes its step across the threshold, which the
#: calibration's finite differences need.
EDGE_STEP = 0.1


def edge_weight(frames: np.ndarray, step: float) -> np.ndarray:
    """How much of a finer-rayed value each pixel of ``frames`` (F, H, W) takes, (F, H, W) float32 in [0, 1]: its
    largest step to a 4-neighbour, 0 at ``step / 2`` or below rising to 1 at ``step``."""
    largest = np.zeros(frames.shape, np.float32)
    rows = np.abs(np.diff(frames, axis=1))
    cols = np.abs(np.diff(frames, axis=2))
    for target, diff in (
        (largest[:, 1:], rows),
        (largest[:, :-1], rows),
        (largest[:, :, 1:], cols),
        (largest[:, :, :-1], cols),
    ):
        np.maximum(target, diff, out=target)
    return np.clip(largest * np.float32(2.0 / step) - np.float32(1.0), 0.0, 1.0)


def _neighbourhood(pixels: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Row-major ``pixels`` of an image of ``shape`` and their 8-neighbours, sorted: a pixel that finer rays find the
    fluid in touches one that coarser rays do."""
    mask = np.zeros(shape, np.bool_)
    mask.flat[pixels] = True
    return np.flatnonzero(binary_dilation(mask, np.ones((3, 3), np.bool_)))


@dataclass(frozen=True)
class FluidRays:
    """The camera rays that can meet the fluid: ``origin``, ``direction`` (M, 3), the ``pixel``
    (row-major index) each belongs to, and the interval [``enter``, ``leave``] (M,) of the ray
    parameter (mm) inside the bore's cylinder and before anything static."""

    origin: np.ndarray
    direction: np.ndarray
    pixel: np.ndarray
    enter: np.ndarray
    leave: np.ndarray


class Renderer:
    """Renders frames of a scene from Eq. 1 coefficients: ``render(coeffs (N, 4)) -> (N, H, W)`` float32.

    ``supersample``: rays per pixel along each axis; ``sun_samples``: directions over the sun's
    disc for the fluid; ``threads``: frames traced at once (default: one per CPU);
    ``batch_frames``: frames per call of the kernel (bounds the per-frame tables' memory);
    ``static_sun_samples``: sun directions for the static scene (fewer build faster, as calibration needs);
    ``edge_supersample``: where > 0, each frame's fluid pixels that step sharply to a neighbour (a highlight's edge,
    the bore's shadow, a glint: what ``supersample`` rays point-sample) traced again with that many rays per axis, as
    a camera's pixel integrates them, and blended in by :func:`edge_weight` (docs/calibration.md, "The sun's angle and
    the renderer's rays per pixel"); ``sun_stride``: each ray shades with every ``sun_stride``-th of the sun's
    directions (a divisor of ``sun_samples``), the rays of a pixel taking turns (the edge rays take one each);
    ``pixels``: where given (row-major indices), the static scene traced in these pixels alone, black elsewhere, and
    the fluid's rays taken from them (the edge rays' renderer: the pixels its parent's fluid rays reach and their
    neighbours; a fraction of the build).
    """

    def __init__(
        self,
        scene: Scene,
        supersample: int = 2,
        sun_samples: int = 4,
        threads: int | None = None,
        batch_frames: int = 256,
        static_sun_samples: int = STATIC_SUN_SAMPLES,
        edge_supersample: int = 0,
        sun_stride: int = 1,
        pixels: np.ndarray | None = None,
    ) -> None:
        for name, value in (
            ("supersample", supersample),
            ("sun_samples", sun_samples),
            ("batch_frames", batch_frames),
            ("static_sun_samples", static_sun_samples),
        ):
            if not 1 <= value <= 4096:
                raise MeniscopeError("renderer", f"{name} must be between 1 and 4096, got {value}")
        self.scene, self.supersample, self.batch_frames = scene, supersample, batch_frames
        self.sun_samples = sun_samples
        if sun_stride < 1 or sun_samples % sun_stride:
            raise MeniscopeError("renderer", f"sun_stride must divide sun_samples ({sun_samples}), got {sun_stride}")
        self.sun_stride = sun_stride
        self.threads = max(1, threads if threads is not None else (os.cpu_count() or 1))
        cam, R = scene.camera, scene.nozzle.radius_mm
        self.shape = (cam.height_px, cam.width_px)
        rays = pixel_rays(scene, supersample)
        h, w, ss = cam.height_px, cam.width_px, supersample
        n = rays.camera_s.shape[0]
        # rays are ordered (row, sub-row, column, sub-column): the pixel each belongs to
        pixel_of = (np.arange(n) // (w * ss * ss)) * w + (np.arange(n) % (w * ss)) // ss
        # rays that can meet the fluid: they enter the bore's cylinder before anything static
        enter, leave = nozzle.cylinder_interval(rays.origin, rays.direction, R)
        enter = np.maximum(enter, rays.camera_s)
        traced = slice(None) if pixels is None else np.flatnonzero(np.isin(pixel_of, pixels))
        static = nozzle.trace(scene, rays.origin[traced], rays.direction[traced], rays.camera_s[traced])
        static_suns = sun_directions(scene, static_sun_samples)
        shaded = nozzle.shade(scene, rays.origin[traced], rays.direction[traced], static, static_suns)
        radiance, static_t = np.zeros(n), np.full(n, -np.inf)  # an untraced ray meets no fluid
        radiance[traced], static_t[traced] = shaded, static.t
        static_pixels = radiance.reshape(h, ss, w, ss).mean(axis=(1, 3)).ravel()  # (H W,)
        glint_pixels, glint_radiance = glints.splats(scene, static_suns)
        np.add.at(static_pixels, glint_pixels, glint_radiance)
        leave = np.minimum(leave, static_t)
        idx = np.flatnonzero(np.isfinite(enter) & (enter < leave))
        self._origin, self._direction = rays.origin[idx], rays.direction[idx]
        self._terms = ray_terms(self._origin, self._direction, R)
        self._enter, self._leave = enter[idx], leave[idx]
        self._static_radiance = radiance[idx]
        self._pixel = pixel_of[idx]  # (M,)
        # per frame only the pixels these rays belong to change; the rest is the static frame
        self._touched, self._slot = np.unique(self._pixel, return_inverse=True)
        self._static_touched = static_pixels[self._touched]
        self._static_frame = np.clip(scene.camera.exposure * static_pixels, 0, 1).astype(np.float32)
        self._suns = sun_directions(scene, sun_samples)
        self._spheres = scene.spheres
        self._intensity = mirror_ball_intensity(
            self._spheres[:, 3], scene.sphere_material.reflectance, scene.light.strength
        )
        self._reach, self._reach_start, self._reach_scale = self._sphere_reach()
        self._edges = (
            Renderer(
                scene,
                edge_supersample,
                sun_samples,
                threads,
                batch_frames,
                static_sun_samples,
                sun_stride=sun_samples,  # a direction each, as Cycles draws one a sample: shading was most of a ray's cost
                pixels=_neighbourhood(self._touched, self.shape),
            )
            if edge_supersample
            else None
        )

    # ---- public -------------------------------------------------------------------------------
    def render(self, coeffs: ArrayLike) -> np.ndarray:
        """Frames for coefficients of shape (N, 4) (d, p, a, b; Eq. 1): float32 (N, H, W) in [0, 1]."""
        coeffs = coefficient_array(coeffs)
        out = np.empty((coeffs.shape[0], *self.shape), np.float32)
        for i in range(0, coeffs.shape[0], self.batch_frames):
            self._render_batch(coeffs[i : i + self.batch_frames], out[i : i + self.batch_frames])
        return out

    def fluid_hits(self, coeffs: ArrayLike) -> np.ndarray:
        """Where the rays that can meet the fluid first meet it, per frame: (N, M, 3) in mm, NaN where a
        ray misses (rays: :attr:`fluid_rays`). What :meth:`render` shades; for checks and figures."""
        coeffs = coefficient_array(coeffs)
        prof = Profiles.build(coeffs, self.scene.nozzle.radius_mm)
        s = np.empty((coeffs.shape[0], self._origin.shape[0]))
        with self._launch():
            kernel.first_hits(
                coeffs,
                prof.value,
                prof.step,
                prof.z_low,
                prof.z_high,
                prof.max_slope,
                self._terms,
                self._enter,
                self._leave,
                self.scene.nozzle.radius_mm,
                s,
            )
        return self._origin + s[..., None] * self._direction

    @property
    def static_frame(self) -> np.ndarray:
        """The scene without the fluid (H, W): the nozzle and its defects as every frame starts, before the sensor."""
        return self._static_frame.reshape(self.shape)

    @property
    def fluid_rays(self) -> FluidRays:
        """The rays that can meet the fluid, as :meth:`fluid_hits` and :meth:`render` trace them."""
        return FluidRays(self._origin, self._direction, self._pixel, self._enter, self._leave)

    @contextmanager
    def _launch(self) -> Iterator[None]:
        """Hold numba's thread pool, sized to this renderer's ``threads``, for one kernel call."""
        with kernel.LAUNCH:
            numba.set_num_threads(min(self.threads, numba.config.NUMBA_NUM_THREADS))
            yield

    def _render_batch(self, coeffs: np.ndarray, out: np.ndarray) -> None:
        """Trace the fluid for frames (F, 4) and write the frames (F, H, W) into ``out``; with edge rays, its steep
        pixels traced again with them and blended in by :func:`edge_weight`."""
        out.reshape(coeffs.shape[0], -1)[:] = self._static_frame
        prof = Profiles.build(coeffs, self.scene.nozzle.radius_mm)
        self._trace(coeffs, prof, np.zeros((0, 0), np.bool_), out)
        if self._edges is not None:
            weight = edge_weight(out, EDGE_STEP)
            flat, finer = weight.reshape(coeffs.shape[0], -1), out.copy()
            self._edges._trace(coeffs, prof, flat[:, self._edges._touched] > 0, finer)
            out += weight * (finer - out)

    def _trace(self, coeffs: np.ndarray, prof: Profiles, only: np.ndarray, out: np.ndarray) -> None:
        """The fluid's pixels of frames (F, 4) traced into ``out`` (F, H, W), holding the static frame there (or,
        where ``only`` (F, P) picks among the touched pixels, the frame as it stands)."""
        n_frames = coeffs.shape[0]
        nz, fluid = self.scene.nozzle, self.scene.fluid
        with self._launch():
            kernel.trace(
                coeffs,
                prof.value,
                prof.step,
                prof.slope,
                prof.slope_step,
                prof.z_low,
                prof.z_high,
                prof.max_slope,
                prof.convex,
                self._origin,
                self._direction,
                self._terms,
                self._enter,
                self._leave,
                self._static_radiance,
                self._slot,
                1.0 / self.supersample**2,
                self._touched,
                self._static_touched,
                self.scene.camera.exposure,
                self._suns,
                self.sun_stride,
                fluid.roughness,
                fluid.reflectance,
                self.scene.light.strength,
                nz.radius_mm,
                nz.outer_radius_mm,
                nz.bore_depth_mm,
                self._spheres,
                self._intensity,
                self._reach,
                self._reach_start,
                self._reach_scale,
                CULL_MIN_COS_VIEW,
                only,
                out.reshape(n_frames, -1),
            )

    def _sphere_reach(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which sphere can light which fluid hit: per ray m, interval i along it and sphere k, the
        least tilt of the surface normal (from straight down) at which sphere k adds more than
        :data:`FAINTEST` to the ray; returned as an int16 table (M, I, K) in units of ``kernel.REACH_UNIT`` (rounded down), with the
        start (M,) and intervals per mm (M,) of the segment where the ray can meet the fluid (|z| <= R).

        Rigorous bound: at an interval's start the half-vector of the view and the sphere makes
        the angle beta with straight down; across the interval the direction to the sphere turns
        by at most the angle the interval subtends from the sphere's centre, and the half-vector
        by at most that over |v + w|. A normal tilted by ``tilt`` is then at least
        ``beta - change - tilt`` from the half-vector, and the reflection is invisible beyond the
        angle where GGX's D falls below FAINTEST over the brightest it could be there: the GGX
        peak (n.v >= CULL_MIN_COS_VIEW) times the sphere's intensity over its nearest distance squared.
        """
        M, K = self._origin.shape[0], self._spheres.shape[0]
        R, n_int = self.scene.nozzle.radius_mm, CULL_SAMPLES - 1
        o, d = self._origin, self._direction
        dz = np.where(d[:, 2] == 0, 1e-12, d[:, 2])
        z_a, z_b = (-R - o[:, 2]) / dz, (R - o[:, 2]) / dz
        lo = np.maximum(self._enter, np.minimum(z_a, z_b))
        hi = np.maximum(np.minimum(self._leave, np.maximum(z_a, z_b)), lo + 1e-9)
        if not K or not M:
            return np.zeros((M, n_int, K), np.int16), lo, n_int / (hi - lo)
        length = (hi - lo) / n_int  # (M,) of each interval
        reach = np.empty((M, n_int, K), np.int16)
        for rows in range(0, M, REACH_CHUNK):  # (chunk, I, K, 3) temporaries stay in cache; the same bits as one go
            at = slice(rows, rows + REACH_CHUNK)
            reach[at] = self._reach_units(o[at], d[at], lo[at], length[at], n_int)
        return reach, lo, n_int / (hi - lo)

    def _reach_units(self, o: np.ndarray, d: np.ndarray, lo: np.ndarray, length: np.ndarray, n_int: int) -> np.ndarray:
        """:meth:`_sphere_reach`'s table for the rays with origins ``o`` and directions ``d`` whose fluid segment
        starts at ``lo`` with intervals of ``length``: (m, I, K) int16."""
        start = lo[:, None] + length[:, None] * np.arange(n_int)  # (M, I)
        p = o[:, None, :] + start[..., None] * d[:, None, :]  # (M, I, 3) interval starts
        centre, radius = self._spheres[:, :3], self._spheres[:, 3]
        rel = centre - p[:, :, None, :]  # (M, I, K, 3)
        dist = np.linalg.norm(rel, axis=-1)
        w = rel / dist[..., None]
        along = np.clip(np.einsum("mikc,mc->mik", rel, d), 0.0, length[:, None, None])
        nearest = np.linalg.norm(rel - along[..., None] * d[:, None, None, :], axis=-1)  # segment to centre
        turn = 2 * np.arctan(length[:, None, None] / (2 * np.maximum(nearest, 1e-12)))  # w turns at most this
        half = w - d[:, None, None, :]  # v + w, v = -d
        half_len = np.linalg.norm(half, axis=-1)
        beta = np.arccos(np.clip(-half[..., 2] / half_len, -1.0, 1.0))
        room = half_len - turn
        change = np.where(room > turn, np.arcsin(np.clip(turn / np.maximum(room, 1e-12), 0.0, 1.0)), np.pi)
        fluid, alpha = self.scene.fluid, self.scene.fluid.roughness
        brightest = (
            fluid.reflectance
            / (np.pi * alpha**2)
            / (4 * CULL_MIN_COS_VIEW)
            * mirror_ball_intensity(radius, self.scene.sphere_material.reflectance, self.scene.light.strength)
            / np.maximum(nearest, 2 * radius) ** 2
        )  # (M, I, K)
        ratio = np.minimum(FAINTEST / brightest, 1.0) / 2  # D / D_max below which it is invisible
        lobe = np.arctan(alpha * np.sqrt(np.maximum(ratio**-0.5 - 1.0, 0.0)))
        units = np.floor((beta - change - lobe) / kernel.REACH_UNIT)
        return np.clip(units, -32768, 32767).astype(np.int16)
