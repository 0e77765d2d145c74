"""Window inversion by synthesis: a window's Eq. 1 motion refined on its frames through the renderer recovers
the true motion from a poor start, through an unknown exposure and focus; its start undoes the window offset."""
from __future__ import annotations

import numpy as np
import pytest

from service import DEFAULT_SCENE
from service.analysis.synthesis import refine_window, standard_errors, start_motion
from service.camera_effects import CameraEffects
from service.physics import WindowTruth
from service.render.renderer import Renderer
from service.scene import Scene

FPS = 19000.0
TRUE = WindowTruth(d=0.01, p=-0.08, A1=0.018, g1=400.0, f1=1400.0, phi1=1.0, A2=0.007, g2=900.0, f2=3200.0, phi2=4.0)
T = np.arange(5, 150) / FPS  # after the ejection's transient, s since the window start


@pytest.fixture(scope="module")
def renderer() -> Renderer:
    """One ray per pixel and sun direction: the cheapest renderer, for the recording and the search alike."""
    return Renderer(Scene.load(DEFAULT_SCENE), supersample=1, sun_samples=1)


def frames_of(renderer: Renderer, motion: WindowTruth, camera: CameraEffects, seed: int = 0) -> np.ndarray:
    """A window's ROI frames as a camera stores them."""
    return camera.apply(renderer.render(motion.coefficients(T).to_array()), np.random.default_rng(seed))


def relative(found: float, true: float) -> float:
    return abs(found - true) / abs(true)


def test_refinement_recovers_the_motion_from_a_poor_start_through_gain_offset_blur_and_noise(renderer):
    camera = CameraEffects(gain=0.8, offset=0.02, blur_sigma_px=0.6, full_well_e=16000.0, read_noise_dn=5.0,
                           bit_depth=12)
    frames = frames_of(renderer, TRUE, camera)
    start = WindowTruth(d=0.013, p=-0.06, A1=0.011, g1=250.0, f1=1390.0, phi1=1.4, A2=0.004, g2=600.0, f2=3150.0,
                        phi2=3.5)
    refined = refine_window(renderer, frames, T, start).motion
    assert relative(refined.f1, TRUE.f1) < 1e-3 and relative(refined.g1, TRUE.g1) < 0.02
    assert relative(refined.A1, TRUE.A1) < 0.03
    R = 0.25
    assert abs((refined.d + refined.p * R) - (TRUE.d + TRUE.p * R)) < 5e-4  # mm: 0.5 um
    assert relative(refined.f2, TRUE.f2) < 5e-3


def test_refinement_lowers_the_pixel_residual_and_reports_its_search(renderer):
    frames = frames_of(renderer, TRUE, CameraEffects(bit_depth=12, blur_sigma_px=0.7, full_well_e=16000.0))
    start = WindowTruth(**{**TRUE.as_dict(), "A1": 0.012, "g1": 600.0})
    refined = refine_window(renderer, frames, T, start)
    assert refined.rms < 0.2 * refined.rms_start
    assert 0 < refined.evaluations <= 18 + 5 * 100  # one render per start tried, then per LM evaluation one and per Jacobian four
    assert refined.blur_sigma_px == pytest.approx(0.7, abs=0.1)



def test_the_pixel_fit_s_standard_errors_grow_with_the_noise_and_cover_the_truth(renderer):
    """A refined window's intervals come from its pixel fit (s^2 (J'J)^-1): wider on a noisier camera, and, where
    the noise dominates the search's own tolerance and the 12-bit rounding, the truth within a few standard errors
    of what was found."""
    errors = {}
    for read_noise in (2.0, 20.0):
        camera = CameraEffects(bit_depth=12, blur_sigma_px=0.7, full_well_e=16000.0, read_noise_dn=read_noise)
        frames = frames_of(renderer, TRUE, camera, seed=1)
        refined = refine_window(renderer, frames, T, TRUE)
        errors[read_noise] = standard_errors(renderer, frames, T, refined)
        f_error, g_error = errors[read_noise][4], errors[read_noise][3]
        assert 0 < f_error < 0.01 * TRUE.f1 and 0 < g_error < 0.5 * TRUE.g1
    assert abs(refined.motion.f1 - TRUE.f1) < 4 * f_error and abs(refined.motion.g1 - TRUE.g1) < 4 * g_error
    assert np.all(errors[20.0][:10] > errors[2.0][:10])

def test_the_start_undoes_the_window_offset_of_the_per_frame_fits():
    start = start_motion(TRUE.coefficients(T).to_array(), T, FPS)
    for name, value in TRUE.as_dict().items():
        assert getattr(start, name) == pytest.approx(value, rel=1e-6, abs=1e-9), name
