"""Window inversion by synthesis: a window's Eq. 1 motion refined on its frames through the renderer recovers
the true motion from a poor start, through an unknown exposure and focus, and from the mirrored surface; its
start undoes the window offset and reads the modes a per-frame start missed from the frames; implausible
motions are told apart."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.ndimage import gaussian_filter
from threadpoolctl import threadpool_limits

from service import DEFAULT_SCENE
from service.analysis.fit import fit_window
from service.analysis.offline import _with_pixel_intervals
from service.analysis.results import ModeEstimate, WindowResult
from service.camera_effects import CameraEffects
from service.inverse.synthesis import (
    _SAGS,
    _SCALE,
    SUN_SAMPLES,
    _along_sag,
    _canonical,
    _coefficient_derivatives,
    _coefficients,
    _motion,
    _motion_covariance,
    _point,
    _Problem,
    covariance,
    frames_start,
    moving_pixels,
    plausible,
    refine_window,
    start_motion,
    window_start,
)
from service.physics import CoefficientRanges, WindowMotion
from service.render.renderer import Renderer
from service.scene import Scene

FPS = 19000.0
TRUE = WindowMotion(d=0.01, p=-0.08, A1=0.018, g1=400.0, f1=1400.0, phi1=1.0, A2=0.007, g2=900.0, f2=3200.0, phi2=4.0)
T = np.arange(5, 150) / FPS  # after the ejection's transient, s since the window start


@pytest.fixture(scope="module")
def renderer() -> Renderer:
    """One ray per pixel and sun direction: the cheapest renderer, for the recording and the search alike."""
    return Renderer(Scene.load(DEFAULT_SCENE), supersample=1, sun_samples=1)


def frames_of(renderer: Renderer, motion: WindowMotion, camera: CameraEffects, seed: int = 0) -> np.ndarray:
    """A window's ROI frames as a camera stores them."""
    return camera.apply(renderer.render(motion.coefficients(T).to_array()), np.random.default_rng(seed))


def relative(found: float, true: float) -> float:
    return abs(found - true) / abs(true)


def test_refinement_recovers_the_motion_from_a_poor_start_through_gain_offset_blur_and_noise(renderer):
    camera = CameraEffects(
        gain=0.8, offset=0.02, blur_sigma_px=0.6, full_well_e=16000.0, read_noise_dn=5.0, bit_depth=12
    )
    frames = frames_of(renderer, TRUE, camera)
    start = WindowMotion(
        d=0.013, p=-0.06, A1=0.011, g1=250.0, f1=1390.0, phi1=1.4, A2=0.004, g2=600.0, f2=3150.0, phi2=3.5
    )
    refined = refine_window(renderer, frames, T, start).motion
    assert relative(refined.f1, TRUE.f1) < 1e-3 and relative(refined.g1, TRUE.g1) < 0.02
    assert relative(refined.A1, TRUE.A1) < 0.03
    R = 0.25
    assert abs((refined.d + refined.p * R) - (TRUE.d + TRUE.p * R)) < 5e-4  # mm: 0.5 um
    assert relative(refined.f2, TRUE.f2) < 5e-3


def test_refinement_lowers_the_pixel_residual_and_reports_its_search(renderer):
    frames = frames_of(renderer, TRUE, CameraEffects(bit_depth=12, blur_sigma_px=0.7, full_well_e=16000.0))
    start = WindowMotion(**{**TRUE.as_dict(), "A1": 0.012, "g1": 600.0})
    refined = refine_window(renderer, frames, T, start)
    assert refined.rms < 0.2 * refined.rms_start
    # one render per start variant tried (two starts), then per LM evaluation one and per Jacobian four, and one
    # for the mirror, of at most two searches from each start
    assert 0 < refined.evaluations <= 2 * 18 + 4 * (5 * 100 + 1)
    assert refined.blur_sigma_px == pytest.approx(0.7, abs=0.1)


def test_the_pixel_fit_s_covariance_grows_with_the_noise_and_covers_the_truth(renderer):
    """A refined window's intervals come from its pixel fit's covariance: wider on a noisier camera, and, where
    the noise dominates the search's own tolerance and the 12-bit rounding, the truth within a few standard errors
    of what was found; estimated from the image's tiles, dozens of them on this window."""
    errors = {}
    for read_noise in (2.0, 20.0):
        camera = CameraEffects(bit_depth=12, blur_sigma_px=0.7, full_well_e=16000.0, read_noise_dn=read_noise)
        frames = frames_of(renderer, TRUE, camera, seed=1)
        refined = refine_window(renderer, frames, T, TRUE)
        found, clusters = covariance(renderer, frames, T, refined)
        errors[read_noise] = np.sqrt(np.diag(found))
        f_error, g_error = errors[read_noise][4], errors[read_noise][3]
        assert 0 < f_error < 0.01 * TRUE.f1 and 0 < g_error < 0.5 * TRUE.g1 and clusters >= 10
    assert abs(refined.motion.f1 - TRUE.f1) < 4 * f_error and abs(refined.motion.g1 - TRUE.g1) < 4 * g_error
    assert np.all(errors[20.0][:10] > errors[2.0][:10])


def test_the_start_undoes_the_window_offset_of_the_per_frame_fits():
    start = start_motion(TRUE.coefficients(T).to_array(), T, FPS)
    for name, value in TRUE.as_dict().items():
        assert getattr(start, name) == pytest.approx(value, rel=1e-6, abs=1e-9), name


def test_the_frames_give_the_start_the_modes_a_per_frame_start_missed(renderer):
    """A per-frame start that took a slow swing for mode 1 and a fast transient for its decay (as the network's
    did on a window of s101_lab) gets its frequencies, decays and phases (up to pi) from the frames."""
    frames = frames_of(renderer, TRUE, CameraEffects(bit_depth=12, blur_sigma_px=0.7, full_well_e=16000.0))
    missed = replace(TRUE, A1=0.1, g1=4000.0, f1=700.0, phi1=0.0, A2=0.04, g2=8000.0, f2=1600.0, phi2=0.0)
    start = frames_start(missed, frames, T)
    assert relative(start.f1, TRUE.f1) < 0.01 and relative(start.f2, TRUE.f2) < 0.02
    assert relative(start.g1, TRUE.g1) < 0.3
    assert np.cos(2 * (start.phi1 - TRUE.phi1)) > 0.9 and np.cos(2 * (start.phi2 - TRUE.phi2)) > 0.9
    assert 0.003 <= start.A1 <= 0.03 and 0.0015 <= start.A2 <= 0.015  # within the coefficient ranges
    assert (start.d, start.p) == (missed.d, missed.p)


def test_a_motion_is_plausible_inside_the_coefficient_ranges_with_its_modes_in_order_below_nyquist():
    assert plausible(TRUE, T)
    for wrong in (dict(A1=0.1), dict(A2=0.5, g2=100.0), dict(f2=12000.0), dict(f1=100.0), dict(f1=3300.0), dict(p=0.3)):
        assert not plausible(replace(TRUE, **wrong), T), wrong


def test_the_search_leaves_the_mirrored_surface_for_the_true_one(renderer):
    """The surface mirrored about its rim plane (sag and modes of the other sign) is a start the search would
    stay near (without the second LM run from the mirror of where it ends, it ends at p = +0.07)."""
    frames = frames_of(renderer, TRUE, CameraEffects(bit_depth=12, blur_sigma_px=0.7, full_well_e=16000.0))
    mirror = replace(TRUE, p=-TRUE.p, phi1=TRUE.phi1 + np.pi, phi2=TRUE.phi2 + np.pi)
    refined = refine_window(renderer, frames, T, mirror).motion
    assert refined.p == pytest.approx(TRUE.p, abs=0.01) and relative(refined.f1, TRUE.f1) < 1e-3


def test_a_refined_window_reports_the_pixel_fit_s_intervals_for_each_mode_and_the_offset_and_null_where_unidentifiable():
    """Each reported mode takes the frequency, decay and amplitude intervals of the motion's mode nearest in
    frequency, the offset d + p R its own with d's and p's covariance, at Student's t with clusters - 1 degrees of
    freedom (2.093 for 20 clusters at 95 %); an unidentifiable direction (infinite covariance) gives the whole band
    0 to Nyquist for a frequency, as the window fit does, and no other interval, which the reason names."""
    result = fit_window(TRUE.coefficients(T).centre(0.25), FPS)
    variances = np.zeros(11)
    variances[[0, 1, 2, 3, 4, 6, 7, 8]] = 1e-6, 1e-4, 1e-8, 4.0, 0.25, 4e-8, 36.0, 2.25  # d p A1 g1 f1 A2 g2 f2
    found = np.diag(variances)
    found[0, 1] = found[1, 0] = -5e-6  # d and p trade against each other
    intervals = _with_pixel_intervals(result, TRUE, found, 20, FPS, 0.95, 0.25)
    assert (result.intervals, intervals.intervals) == ("fit", "pixels")  # the report says where they come from
    first, second = intervals.modes
    z = 2.093
    assert first.frequency_ci_hz == pytest.approx(
        (first.frequency_hz - z * 0.5, first.frequency_hz + z * 0.5), abs=1e-3
    )
    assert first.decay_rate_ci_per_s == pytest.approx(
        (first.decay_rate_per_s - z * 2, first.decay_rate_per_s + z * 2), abs=1e-2
    )
    assert first.amplitude_ci_mm == pytest.approx(
        (first.amplitude_mm - z * 1e-4, first.amplitude_mm + z * 1e-4), abs=1e-6
    )
    assert second.frequency_ci_hz == pytest.approx(
        (second.frequency_hz - z * 1.5, second.frequency_hz + z * 1.5), abs=1e-2
    )
    offset_error = np.sqrt(1e-6 + 0.25**2 * 1e-4 - 2 * 0.25 * 5e-6)
    assert intervals.offset_ci_mm == pytest.approx(
        (intervals.offset_mm - z * offset_error, intervals.offset_mm + z * offset_error), abs=1e-7
    )
    found[:, [6, 7, 8]] = found[[6, 7, 8], :] = np.inf
    unknown = _with_pixel_intervals(result, TRUE, found, 20, FPS, 0.95, 0.25)
    assert unknown.modes[1].frequency_ci_hz == (0.0, FPS / 2) and unknown.modes[1].decay_rate_ci_per_s is None
    assert unknown.modes[1].amplitude_ci_mm is None and unknown.modes[0].amplitude_ci_mm is not None
    assert "mode 2 decay_rate_ci_per_s not finite" in unknown.reason


def test_a_refined_window_is_the_same_bits_whatever_blas_threads_its_process_has(renderer):
    """Each runner's processes have their own BLAS threads (a forked pool's one per core, Dask's workers one): a
    long dot product summed in per-thread pieces differs in its last bits, and the search's path and the pixel
    fit's covariance with it. A window refined where BLAS has one thread and where it has two is the same."""
    frames, t = (
        frames_of(renderer, TRUE, CameraEffects(bit_depth=12, blur_sigma_px=0.7, full_well_e=16000.0))[:40],
        T[:40],
    )
    start = WindowMotion(**{**TRUE.as_dict(), "A1": 0.012, "g1": 600.0})
    found = []
    for threads in (1, 2):
        with threadpool_limits(threads, user_api="blas"):
            refined = refine_window(renderer, frames, t, start)
            found.append((refined, covariance(renderer, frames, t, refined)[0].tobytes()))
    assert found[0] == found[1]


def test_the_search_reads_the_pixels_the_motion_moves_with_a_margin_and_every_pixel_of_a_still_window(renderer):
    """The search's pixels: every pixel the true motion changes (seen through noise) and a margin about them, not
    the static nozzle and bore; a noiseless window where nothing moves keeps every pixel (nothing tells them apart)."""
    camera = CameraEffects(full_well_e=20000.0, read_noise_dn=2.0, bit_depth=12)
    clean = renderer.render(TRUE.coefficients(T).to_array())
    pixels = moving_pixels(frames_of(renderer, TRUE, camera).astype(np.float64))
    changed = clean.std(axis=0) > 0.05 * clean.std(axis=0).max()
    assert pixels[changed].all() and 0.02 < pixels.mean() < 0.5
    still = frames_of(renderer, replace(TRUE, A1=0.0, A2=0.0), CameraEffects(bit_depth=12))
    assert moving_pixels(still.astype(np.float64)).all()


def fitted_result(modes: list[tuple[float, float, float, float]], offset_mm: float | None) -> WindowResult:
    """A window fit's result with ``modes`` (amplitude, decay, frequency, phase), dominant first."""
    return WindowResult(
        index=0,
        start_frame=0,
        end_frame=190,
        status="ok",
        offset_mm=offset_mm,
        modes=[
            ModeEstimate(amplitude_mm=a, decay_rate_per_s=g, frequency_hz=f, phase_rad=phi) for a, g, f, phi in modes
        ],
    )


def test_the_start_from_a_window_fit_takes_its_modes_by_frequency_and_its_offset_with_the_per_frame_sag():
    """Mode 1 is the fit's lower mode whichever it found dominant (slower to decay); d is the fitted offset d + p R less the per-frame
    sag's p R; a fit of one mode gets mode 2 at the membrane's ratio; a fit without a mode gives no start."""
    R, p = 0.25, -0.08
    coefficients = np.tile([0.0, p, 0.0, 0.0], (40, 1))
    two = fitted_result([(0.007, 300.0, 3200.0, 4.0), (0.018, 400.0, 1400.0, 1.0)], offset_mm=TRUE.d + p * R)
    assert window_start(two, coefficients, R) == pytest.approx(replace(TRUE, g2=300.0))
    one = window_start(fitted_result([(0.018, 400.0, 1400.0, 1.0)], 0.0), coefficients, R)
    assert one.f2 == pytest.approx(1400.0 * 5.520078110286311 / 2.404825557695773) and one.A2 < one.A1
    assert window_start(fitted_result([], 0.0), coefficients, R) is None


def test_from_a_window_fit_s_start_the_search_finds_the_motion_where_the_per_frame_start_is_shrunk(renderer):
    """The window model's fit is not shrunk, and is searched as it is (no amplified variants): from it the search
    ends at the truth although the per-frame start's amplitudes are a third of the truth's."""
    frames = frames_of(renderer, TRUE, CameraEffects(bit_depth=12, blur_sigma_px=0.7, full_well_e=16000.0))
    fitted = replace(TRUE, A1=0.016, g1=430.0, f1=1402.0, d=0.012)
    refined = refine_window(renderer, frames, T, replace(TRUE, A1=0.006, A2=0.002), fitted).motion
    assert relative(refined.f1, TRUE.f1) < 1e-3 and relative(refined.g1, TRUE.g1) < 0.02
    assert relative(refined.A1, TRUE.A1) < 0.03 and abs(refined.d - TRUE.d) < 1e-3


def test_the_search_sees_a_near_mirror_s_sun_as_a_disc_not_as_its_renderer_s_four_points():
    """A real camera (and Cycles) sees the sun's whole disc. On the near-mirror end of the fluids (GGX alpha
    0.003) renders at the search's sun directions of motions drawn over the coefficient ranges, blurred as the lab
    camera, lie within 7 % (relative RMS over the pixels that move) of renders at 64 directions; at the renderer's
    default 4 directions each highlight is four points, over 12 % off."""
    data = Scene.load(DEFAULT_SCENE).model_dump(mode="json")
    scene = Scene.from_dict({**data, "fluid": {**data["fluid"], "roughness": 0.003}})
    ranges, rng = CoefficientRanges(), np.random.default_rng(0)
    coefficients = np.stack([rng.uniform(*bounds, 8) for bounds in (ranges.d, ranges.p, ranges.a, ranges.b)], 1)

    def seen(sun_samples: int) -> np.ndarray:
        renderer = Renderer(scene, supersample=1, sun_samples=sun_samples, threads=1, static_sun_samples=1)
        return gaussian_filter(renderer.render(coefficients).astype(np.float64), (0, 0.7, 0.7))

    truth = seen(64)
    moving = truth.std(axis=0) > 0.005
    scale = np.sqrt(np.mean((truth - truth.mean(axis=0))[:, moving] ** 2))

    def off(sun_samples: int) -> float:
        return float(np.sqrt(np.mean((seen(sun_samples) - truth)[:, moving] ** 2)) / scale)

    assert off(SUN_SAMPLES) < 0.07 and off(4) > 0.12


@settings(max_examples=25, deadline=None)
@given(blur=st.one_of(st.floats(10.001, 1e300), st.sampled_from([np.inf, -np.inf, np.nan, -5e9])))
def test_a_search_step_to_an_absurd_blur_is_a_bad_fit_not_a_crash(renderer, blur: float) -> None:
    """LM's steps are unbounded: a blur no camera has (sigma 5e9 px asked scipy for a 161 GiB kernel) gets residuals
    as bad as a black window's, finite and worse than the true motion's, so the search steps back."""
    camera = CameraEffects(blur_sigma_px=0.7, bit_depth=12)
    problem = _Problem(renderer, frames_of(renderer, TRUE, camera), T)
    absurd = problem.residuals(_point(TRUE, blur))
    assert np.all(np.isfinite(absurd))
    assert np.mean(absurd**2) > np.mean(problem.residuals(_point(TRUE, 0.7)) ** 2)


@settings(max_examples=40, deadline=None)
@given(
    amplitudes=st.tuples(st.floats(1e-6, 0.2), st.floats(1e-6, 0.2)),
    decays=st.tuples(st.floats(0.0, 2e4), st.floats(-2e4, 2e4)),
    frequencies=st.tuples(st.floats(50.0, 9000.0), st.floats(-9000.0, 9000.0)),
    phases=st.tuples(st.floats(-10.0, 10.0), st.floats(-10.0, 10.0)),
)
def test_the_chain_rule_of_eq1_matches_finite_differences_at_extreme_motions(
    amplitudes: tuple[float, float],
    decays: tuple[float, float],
    frequencies: tuple[float, float],
    phases: tuple[float, float],
) -> None:
    """The search's Jacobian is each frame's d(pixels)/d(d, p, a, b) times d(d, p, a, b)/d(motion) of Eq. 1, exact:
    central differences of the per-frame coefficients agree with it over the window at the coefficient ranges'
    amplitudes, decays to 20,000 /s (of either sign: the search's decay stands for its absolute value; mode 2's is
    mode 1's plus its own, so mode 1's moves b too), frequencies to Nyquist and beyond (negative too) and any phase."""
    params = np.array([0.02, -0.1, amplitudes[0], decays[0], frequencies[0], phases[0]] + [amplitudes[1], decays[1]])
    params = np.append(params, [frequencies[1], phases[1]])
    exact = _coefficient_derivatives(params, T)
    for k, step in enumerate(1e-4 * _SCALE[:10]):
        if k in (3, 7) and abs(params[k]) < step:
            continue  # |decay| has no derivative at 0
        up, down = params.copy(), params.copy()
        up[k] += step
        down[k] -= step
        numeric = (_coefficients(up, T) - _coefficients(down, T)) / (2 * step)
        scale = np.abs(numeric).max() + np.abs(exact[:, k]).max() + 1e-12
        np.testing.assert_allclose(exact[:, k], numeric, rtol=0, atol=1e-5 * scale, err_msg=f"parameter {k}")


@settings(max_examples=60, deadline=None)
@given(point=st.lists(st.floats(-1e4, 1e4), min_size=11, max_size=11))
def test_no_point_of_the_search_gives_mode_2_the_slower_decay(point: list[float]) -> None:
    """scene.md's membrane: mode 2 decays faster than mode 1 (mode 1 is the dominant one). Wherever LM's unbounded
    steps go, the motion it stands for keeps that order, and a motion that broke it starts the search from both
    modes at mode 1's rate."""
    motion = _canonical(_motion(np.array(point) * _SCALE))
    assert 0 <= motion.g1 <= motion.g2
    slower = replace(TRUE, g2=0.5 * TRUE.g1)
    assert _canonical(_motion(_point(slower, 0.7) * _SCALE)).g2 == pytest.approx(TRUE.g1)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), unpinned=st.sampled_from([None, 3, 7, 10]))
def test_the_motion_s_covariance_is_the_search_s_carried_through_g2_as_g1_plus_its_own(
    seed: int, unpinned: int | None
) -> None:
    """T C T' with T the Jacobian of the motion (g2 = g1 + excess) in the search's parameters; a parameter the pixels
    do not pin down (an infinite row and column) stays infinite, and nothing becomes NaN."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(11, 11))
    searched = a @ a.T
    transform = np.eye(11)
    transform[7, 3] = 1.0
    expected = transform @ searched @ transform.T
    if unpinned is not None:
        searched[unpinned, :] = searched[:, unpinned] = np.inf
    found = _motion_covariance(searched)
    assert not np.isnan(found).any()
    finite = np.isfinite(found)
    np.testing.assert_allclose(found[finite], expected[finite], rtol=1e-12, atol=1e-12)
    if unpinned is not None:
        assert not finite[unpinned].any() and (unpinned not in (3, 7) or not finite[7].any())


@pytest.mark.parametrize("wrong_by", [0.2, 0.12, -0.1])
def test_a_start_at_the_wrong_sag_is_moved_along_its_offset_to_the_frames_sag(renderer, wrong_by: float):
    """The window fit gives the centre's offset d + p R, the per-frame method the sag p, and that can be far off
    (of the wrong sign on a Blender window): the search starts from the sag across the coefficient ranges whose
    frames fit best, with the offset kept, not from the per-frame one."""
    frames = frames_of(renderer, TRUE, CameraEffects(bit_depth=12, blur_sigma_px=0.7, read_noise_dn=2.0))
    R = renderer.scene.nozzle.radius_mm
    wrong = replace(TRUE, p=TRUE.p + wrong_by, d=TRUE.d - wrong_by * R)
    moved = _along_sag(_Problem(renderer, frames, T), wrong)
    spacing = np.ptp(CoefficientRanges().p) / (_SAGS - 1)
    assert abs(moved.p - TRUE.p) <= spacing / 2 + 1e-9
    assert moved.d + moved.p * R == pytest.approx(TRUE.d + TRUE.p * R, abs=1e-12)
