"""The ray tracer: hits on the Eq. 1 surface (no missed or false hits), shading against the numpy
reference of the shading model, the bore wall hiding the fluid, extremes, determinism, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.errors import MeniscopeError
from service.physics import L1, L2, CoefficientRanges, displacement, slope
from service.render import Renderer, project
from service.render.camera import pixel_rays
from service.render.meniscus import TABLE_SIZE, TOLERANCE_MM
from service.render.nozzle import sun_visibility
from service.render.shading import specular_sun, sun_directions
from service.scene import Scene


def height_tolerance(c: tuple[float, ...], R: float) -> float:
    """How far from the exact Eq. 1 surface a hit may be, in height (mm): the profile table's linear
    interpolation error, h^2 / 8 max|D''(u)| with max|d^2 J0(l sqrt u) / du^2| = l^4 / 32, plus the
    root tolerance along the ray times the steepest |dF/ds| = 1 + max|dD/dr|."""
    d2 = abs(c[2]) * L1**4 / 32 + abs(c[3]) * L2**4 / 32
    steepest = np.abs(slope(np.linspace(0, R, 2001), *c[1:], R)).max()
    return (1.0 / (TABLE_SIZE - 1)) ** 2 / 8 * d2 + TOLERANCE_MM * (1.0 + steepest) + 1e-9


def _scene_without_artifacts(scene: Scene) -> Scene:
    data = scene.model_dump()
    data["artifacts"]["count"] = 0
    return Scene.from_dict(data)


@pytest.fixture(scope="module")
def renderer(scene: Scene) -> Renderer:
    return Renderer(scene, supersample=1, sun_samples=4)


@pytest.fixture(scope="module")
def bare_renderer(scene: Scene) -> Renderer:
    """One pixel ray, no spheres: each candidate pixel shows exactly one fluid sample."""
    return Renderer(_scene_without_artifacts(scene), supersample=1, sun_samples=4)


amplitude = st.one_of(st.just(0.0), st.floats(1e-9, 1.0), st.floats(-1.0, -1e-9))
coefficients = st.tuples(st.floats(-0.5, 0.5), st.floats(-1.0, 1.0), amplitude, amplitude)


def _gap_along_rays(
    renderer: Renderer, coeffs: np.ndarray, rays: np.ndarray, samples: int = 3000
) -> tuple[np.ndarray, np.ndarray]:
    """Brute force on the fluid rays ``rays`` (indices): the ray parameters (M, S) densely across each
    one's interval and the exact F = z + D(r) there (Eq. 1 by scipy; F > 0 inside the metal)."""
    fr, R = renderer.fluid_rays, renderer.scene.nozzle.radius_mm
    enter, leave = fr.enter[rays], fr.leave[rays]
    s = enter[:, None] + np.linspace(0.0, 1.0, samples) * (leave - enter)[:, None]  # (M, S)
    p = fr.origin[rays, None, :] + s[..., None] * fr.direction[rays, None, :]
    r = np.minimum(np.hypot(p[..., 0], p[..., 1]), R)
    return s, p[..., 2] + displacement(r, *coeffs, R)


@settings(max_examples=60, deadline=None)
@given(coefficients)
def test_every_hit_lies_on_the_eq1_surface_inside_the_bore(renderer: Renderer, c: tuple[float, ...]) -> None:
    hits = renderer.fluid_hits(np.array([c]))[0]
    found = ~np.isnan(hits[:, 0])
    R = renderer.scene.nozzle.radius_mm
    r = np.hypot(hits[found, 0], hits[found, 1])
    assert np.all(r <= R * (1 + 1e-9))
    assert np.all(np.abs(hits[found, 2] + displacement(r, *c, R)) <= height_tolerance(c, R))


@settings(max_examples=20, deadline=None)
@given(coefficients)
def test_no_ray_passes_into_the_metal_before_its_hit_grazing_rays_included(
    renderer: Renderer, c: tuple[float, ...]
) -> None:
    """First hits, no missed ones: along every ray, no point before its hit (or anywhere, for a ray
    that misses) lies inside the exact surface by more than the height tolerance."""
    coeffs = np.array(c)
    rays = np.arange(0, renderer.fluid_rays.enter.size, 3)
    hits = renderer.fluid_hits(coeffs[None])[0, rays]
    hit_s = np.einsum("mc,mc->m", hits - renderer.fluid_rays.origin[rays], renderer.fluid_rays.direction[rays])
    s, gap = _gap_along_rays(renderer, coeffs, rays)
    tol = height_tolerance(c, renderer.scene.nozzle.radius_mm)
    # the height field spans r <= R only (scene.md): rays entering the bore's cylinder already below the
    # surface (through the side of a column bulging out of the outlet) meet no modelled surface first
    from_air = gap[:, 0] < -tol
    before = s < np.where(np.isnan(hit_s), np.inf, hit_s)[:, None]
    deepest = np.where(before, gap, -np.inf).max(axis=1)[from_air]
    assert np.all(deepest <= tol), f"{np.sum(deepest > tol)} rays pass {deepest.max():.3g} mm into the metal"
    # and a ray that clearly enters the metal is never reported as a miss
    assert not np.any((np.isnan(hit_s) & (gap.max(axis=1) > tol))[from_air])


def test_bore_wall_hides_the_fluid_inside_the_bore(renderer: Renderer) -> None:
    """A surface deep in the bore is seen only through the outlet: every hit's ray crosses z = 0 inside r < R."""
    R = renderer.scene.nozzle.radius_mm
    hits = renderer.fluid_hits(np.array([[-0.3, 0.1, 0.02, -0.01]]))[0]
    found = ~np.isnan(hits[:, 0])
    assert found.any()
    o, d = renderer.fluid_rays.origin[found], renderer.fluid_rays.direction[found]
    cross = o + (-o[:, 2] / d[:, 2])[:, None] * d
    assert np.all(np.hypot(cross[:, 0], cross[:, 1]) < R * (1 + 1e-9))


def _down_normal(points: np.ndarray, c: np.ndarray, R: float) -> np.ndarray:
    """Unit normals facing the air of z = -D(r) (Eq. 1) at points (M, 3): (-D'(r) r_hat, -1), normalised."""
    rr = np.hypot(points[:, 0], points[:, 1])
    g = -slope(rr, *c[1:], R) / np.maximum(rr, 1e-300)
    normal = np.column_stack([g * points[:, 0], g * points[:, 1], -np.ones_like(g)])
    return normal / np.linalg.norm(normal, axis=1, keepdims=True)


def _second_points(
    origin: np.ndarray, direction: np.ndarray, c: np.ndarray, R: float, samples: int = 2000
) -> np.ndarray:
    """Brute force: where mirror rays from surface points first meet the exact surface again inside the
    bore's cylinder, (M, 3), NaN rows for those that never do (sampled from 1e-4 mm to 2 mm)."""
    s = np.geomspace(1e-4, 2.0, samples)
    p = origin[:, None, :] + s[None, :, None] * direction[:, None, :]  # (M, S, 3)
    r = np.hypot(p[..., 0], p[..., 1])
    inside = np.maximum.accumulate(r > R, axis=1) == 0  # before the ray leaves the cylinder
    metal = (p[..., 2] + displacement(np.minimum(r, R), *c, R) > 0) & inside
    first = np.where(metal.any(axis=1), metal.argmax(axis=1), -1)
    out = np.full(origin.shape, np.nan)
    rows = np.flatnonzero(first >= 1)
    lo, hi = s[first[rows] - 1], s[first[rows]]  # air at lo, metal at hi: bisect to the surface
    o, d = origin[rows], direction[rows]
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        x = o + mid[:, None] * d
        in_metal = x[:, 2] + displacement(np.minimum(np.hypot(x[:, 0], x[:, 1]), R), *c, R) > 0
        lo, hi = np.where(in_metal, lo, mid), np.where(in_metal, mid, hi)
    out[rows] = o + lo[:, None] * d
    return out


def test_fluid_pixels_match_the_numpy_shading_model(bare_renderer: Renderer) -> None:
    """Kernel radiance = shading.specular_sun (GGX, Smith, the sun disc, shadowed by the bore) at the hit;
    where its mirror ray meets the fluid again (a concave surface), the reflectance times that at the second point."""
    r, sc = bare_renderer, bare_renderer.scene
    concave = [0.045, -0.188, -0.026, -0.014]  # the centre drawn up into the bore: mirror rays meet it twice
    coeffs = np.array([[0.01, 0.1, 0.02, -0.01], [-0.03, -0.15, -0.01, 0.008], [0.0, 0.0, 0.0, 0.0], concave])
    frames = r.render(coeffs).reshape(len(coeffs), -1)
    hits = r.fluid_hits(coeffs)
    rays, R = r.fluid_rays, sc.nozzle.radius_mm
    suns = sun_directions(sc, 4)
    shade = lambda n, v, vis: specular_sun(n, v, suns, vis, sc.fluid.roughness, sc.fluid.reflectance, sc.light.strength)
    bounced = 0
    for f, c in enumerate(coeffs):
        found = ~np.isnan(hits[f, :, 0])
        p, view = hits[f, found], -rays.direction[found]
        normal = _down_normal(p, c, R)
        expected = shade(normal, view, sun_visibility(sc, p, normal, suns))
        mirror = 2 * np.einsum("mc,mc->m", normal, view)[:, None] * normal - view
        q = _second_points(p, mirror, c, R)
        twice = ~np.isnan(q[:, 0])
        if twice.any():
            n2 = _down_normal(q[twice], c, R)
            expected[twice] = sc.fluid.reflectance * shade(n2, -mirror[twice], sun_visibility(sc, q[twice], n2, suns))
        bounced += twice.sum()
        got = frames[f, rays.pixel[found]]
        close = np.abs(got - np.clip(sc.camera.exposure * expected, 0, 1)) <= 2e-3
        # a sampled second point may differ from the kernel's root at the edges of the twice-hit region
        assert close.mean() >= 0.995, f"frame {f}: {np.sum(~close)} of {close.size} pixels differ"
    assert bounced > 50  # the concave frame exercises the second bounce


def test_tiny_amplitudes_render_as_the_flat_surface(renderer: Renderer) -> None:
    flat = renderer.render(np.array([[0.01, 0.05, 0.0, 0.0]]))
    tiny = renderer.render(np.array([[0.01, 0.05, 1e-9, -1e-9]]))
    np.testing.assert_allclose(tiny, flat, atol=1e-5)


@settings(max_examples=40, deadline=None)
@given(coefficients)
def test_frames_are_finite_in_range_float32_at_every_extreme(renderer: Renderer, c: tuple[float, ...]) -> None:
    frame = renderer.render(np.array([c]))
    assert frame.dtype == np.float32 and frame.shape == (1, *renderer.shape)
    assert np.all(np.isfinite(frame)) and frame.min() >= 0.0 and frame.max() <= 1.0


def test_the_highlight_moves_with_the_surface(renderer: Renderer) -> None:
    """Default ranges keep the sun's highlight on the fluid, and different shapes put it in different places."""
    coeffs = CoefficientRanges().sample(32, np.random.default_rng(1))
    frames = renderer.render(coeffs)
    assert np.all(frames.reshape(32, -1).max(axis=1) > 0.2)
    assert np.unique(frames.reshape(32, -1).argmax(axis=1)).size > 8


def test_threads_and_batches_do_not_change_the_result(scene: Scene) -> None:
    coeffs = CoefficientRanges().sample(20, np.random.default_rng(2))
    one = Renderer(scene, supersample=2, threads=1, batch_frames=7).render(coeffs)
    two = Renderer(scene, supersample=2, threads=2).render(coeffs)
    np.testing.assert_array_equal(one, two)


def test_supersampling_converges(scene: Scene) -> None:
    """Anti-aliasing: more rays per pixel change the image less and less."""
    coeffs = CoefficientRanges().sample(6, np.random.default_rng(3))
    r1, r2, r4 = (Renderer(scene, supersample=s).render(coeffs) for s in (1, 2, 4))
    assert np.abs(r4 - r2).mean() < np.abs(r4 - r1).mean()


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 95), st.integers(0, 95))
def test_a_pixel_ray_projects_back_to_its_pixel_centre(scene: Scene, i: int, j: int) -> None:
    rays = pixel_rays(scene, 1)
    k = i * scene.camera.width_px + j
    col, row = project(scene, rays.origin[k] + 3.0 * rays.direction[k])
    assert col == pytest.approx(j, abs=1e-6) and row == pytest.approx(i, abs=1e-6)


@pytest.mark.parametrize("bad", [np.array([[0.0, 0.0, np.nan, 0.0]]), np.zeros((3, 5)), np.array([[np.inf, 0, 0, 0]])])
def test_bad_coefficients_are_a_clear_error(renderer: Renderer, bad: np.ndarray) -> None:
    with pytest.raises(MeniscopeError, match="coefficients"):
        renderer.render(bad)


def test_bad_settings_are_a_clear_error(scene: Scene) -> None:
    with pytest.raises(MeniscopeError, match="supersample"):
        Renderer(scene, supersample=0)


def test_edge_rays_retrace_only_the_steep_pixels_and_bring_them_to_the_finer_grid(scene: Scene):
    """With ``edge_supersample`` each frame's pixels that step sharply to a neighbour are traced again with more rays:
    every pixel of weight 0 is the 2 x 2 frame's, bit for bit, the fluid's pixels of weight 1 are the 4 x 4 frame's
    whose rays take the sun's directions in turn (the static scene's are not traced again), and the frame is less than
    half as far from 4 x 4 rays (what a camera's pixel integrates) as the 2 x 2 frame is. The static scene is shaded
    with few sun directions: the same in every renderer here, and a fine grid builds in a fraction of the time."""
    from service.render.renderer import EDGE_STEP, edge_weight

    coeffs = CoefficientRanges().sample(12, np.random.default_rng(5))
    coarse = Renderer(scene, supersample=2, static_sun_samples=4).render(coeffs)
    edges = Renderer(scene, supersample=2, edge_supersample=4, static_sun_samples=4).render(coeffs)
    finer = Renderer(scene, supersample=4, sun_stride=4, static_sun_samples=4)  # the renderer's default: 4 directions
    fine = finer.render(coeffs)
    weight = edge_weight(coarse, EDGE_STEP)
    fluid = np.zeros(coarse.shape[1:], np.bool_)
    fluid.flat[finer.fluid_rays.pixel] = True
    whole = (weight == 1) & fluid
    assert whole.any() and ((weight > 0) & (weight < 1)).any()
    np.testing.assert_array_equal(edges[weight == 0], coarse[weight == 0])
    np.testing.assert_allclose(edges[whole], fine[whole], atol=1e-6)
    assert np.abs(edges - fine).sum() < 0.5 * np.abs(coarse - fine).sum()


@settings(max_examples=30, deadline=None)
@given(
    st.floats(0.01, 0.5),
    st.integers(0, 2**32 - 1),
)
def test_edge_weight_rises_from_half_the_step_to_the_step(step: float, seed: int):
    """A pixel's weight is 0 where its largest step to a 4-neighbour is at most half of ``step``, 1 from ``step`` on,
    linear between: two pixels whose steps differ little get weights that differ little."""
    from service.render.renderer import edge_weight

    frames = np.random.default_rng(seed).random((2, 6, 7)).astype(np.float32)
    largest = np.zeros_like(frames)
    padded = np.pad(frames, ((0, 0), (1, 1), (1, 1)), mode="edge")
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        largest = np.maximum(largest, np.abs(padded[:, 1 + dr : 7 + dr, 1 + dc : 8 + dc] - frames))
    np.testing.assert_allclose(edge_weight(frames, step), np.clip(2 * largest / step - 1, 0, 1), atol=1e-5)


def test_rays_sharing_the_suns_directions_in_turn_render_as_rays_shading_with_all_of_them(scene: Scene):
    """With ``sun_stride`` a pixel's 4 x 4 rays each shade with every stride-th of the sun's directions: the frames stay
    within a fifth of 2 x 2 rays' distance from the rays that each shade with all of them, whether each ray takes four
    of the directions or one; a stride that does not divide the directions is refused."""
    coeffs = CoefficientRanges().sample(12, np.random.default_rng(8))
    fine = dict(supersample=4, sun_samples=16, static_sun_samples=4)
    every = Renderer(scene, **fine).render(coeffs)
    coarse = Renderer(scene, supersample=2, sun_samples=16, static_sun_samples=4).render(coeffs)
    for stride in (4, 16):
        shared = Renderer(scene, **fine, sun_stride=stride).render(coeffs)
        assert ((shared - every) ** 2).sum() < 0.2 * ((coarse - every) ** 2).sum()
    with pytest.raises(MeniscopeError, match="sun_stride must divide"):
        Renderer(scene, sun_samples=24, sun_stride=5)


def test_a_renderer_of_the_fluids_pixels_alone_renders_them_as_the_whole_frames_does(scene: Scene):
    """``pixels``: the static scene traced only where a coarser renderer's fluid rays reach and around them (what the
    edge rays' renderer builds): the same fluid rays and, in those pixels, the same frames, bit for bit."""
    from scipy.ndimage import binary_dilation

    coarse = Renderer(scene, supersample=2, sun_samples=4)
    reached = np.zeros(coarse.shape, np.bool_)
    reached.flat[coarse.fluid_rays.pixel] = True
    around = np.flatnonzero(binary_dilation(reached, np.ones((3, 3), np.bool_)))
    whole, part = Renderer(scene, supersample=4), Renderer(scene, supersample=4, pixels=around)
    np.testing.assert_array_equal(part.fluid_rays.pixel, whole.fluid_rays.pixel)
    coeffs = CoefficientRanges().sample(6, np.random.default_rng(2))
    np.testing.assert_array_equal(
        part.render(coeffs).reshape(6, -1)[:, around], whole.render(coeffs).reshape(6, -1)[:, around]
    )
