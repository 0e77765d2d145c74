"""The defects' sun glints seen directly: point sources of the mirror ball's flux, whatever the rays or the roughness."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service import DEFAULT_SCENE
from service.bench.render import flux_ratios, glint_fluxes
from service.calibration.artifacts import glint_positions, with_spheres
from service.render import Renderer, glints
from service.render.camera import focal_px
from service.render.glints import splats
from service.render.renderer import STATIC_SUN_SAMPLES
from service.render.shading import mirror_ball_intensity, sun_directions
from service.scene import Scene


def _scene(spheres: list[list[float]], roughness: float = 0.06) -> Scene:
    data = json.loads(Path(DEFAULT_SCENE).read_text())
    data["camera"].update(width_px=48, height_px=48)
    data["artifacts"].update(
        spheres=[dict(zip(("x", "y", "z", "radius"), s)) for s in spheres],
        material={"roughness": roughness, "reflectance": 0.9},
    )
    return Scene.from_dict(data)


def _glint_excess(scene: Scene, supersample: int) -> np.ndarray:
    """The static frame with the scene's spheres minus the one without them (exposure applied)."""
    with_them = Renderer(scene, supersample=supersample).static_frame
    without = Renderer(with_spheres(scene, np.zeros((0, 4))), supersample=supersample).static_frame
    return with_them.astype(np.float64) - without


@settings(max_examples=4, deadline=None)
@given(st.floats(0.0, 2 * np.pi), st.floats(0.27, 0.32), st.floats(0.004, 0.02), st.sampled_from((0.01, 0.2, 0.48)))
def test_a_defects_glint_has_the_mirror_balls_flux_whatever_the_rays_or_its_roughness(
    angle: float, ring: float, radius: float, roughness: float
) -> None:
    """A sphere far smaller than a pixel on the nozzle face: traced, its body only hides the face behind it (no light
    of its own at 1, 2 or 4 rays a pixel axis: its glint was the rays' luck, 0 to 1,300 DN on Blender Cycles' H
    scene); its glint, where the camera sees it and the sun lights it, adds F E r^2 / 4 over the distance squared and
    the pixel's solid angle to the one pixel holding it; and nothing drawn depends on its roughness."""
    sphere = [ring * np.cos(angle), ring * np.sin(angle), 0.0, radius]
    scene = _scene([sphere], roughness)
    pixel, radiance = splats(scene, sun_directions(scene, STATIC_SUN_SAMPLES))  # the renderer's
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(glints, "splats", lambda *_: (np.zeros(0, np.int64), np.zeros(0)))
        traced = {ss: _glint_excess(scene, ss) for ss in (1, 2, 4)}
    assert all((excess <= 1e-9).all() for excess in traced.values())  # the body hides the face, no more
    drawn = _glint_excess(scene, 2)
    np.testing.assert_array_equal(drawn, _glint_excess(_scene([sphere], 0.3), 2))
    glint = (drawn - traced[2]).ravel()
    if not len(pixel):  # hidden from the camera or in the nozzle's shadow: no glint at all
        assert np.abs(glint).max() < 1e-9
        return
    assert glint[pixel[0]] == pytest.approx(scene.camera.exposure * radiance[0], rel=1e-5)
    assert np.abs(np.delete(glint, pixel[0])).max() < 1e-9
    col, row = glint_positions(scene, np.array([sphere]))[0]  # the pixel holding the glint (ties either side)
    assert abs(pixel[0] % scene.camera.width_px - col) <= 0.5 + 1e-9
    assert abs(pixel[0] // scene.camera.width_px - row) <= 0.5 + 1e-9
    distance = scene.camera.distance_mm
    point_source = mirror_ball_intensity(radius, 0.9, scene.light.strength) / distance**2 * focal_px(scene) ** 2
    assert radiance[0] <= point_source * 1.02  # lit whole near the optical axis, less where the nozzle shades it


def test_spheres_the_camera_cannot_see_add_nothing() -> None:
    """A sphere inside the bore's wall or outside the ROI leaves the static frame as it is."""
    scene = _scene([[0.0, 0.0, 0.3, 0.01], [5.0, 5.0, 0.0, 0.01]])
    pixel, _ = splats(scene, sun_directions(scene, 8))
    assert len(pixel) == 0


def test_the_benchs_glint_comparison_takes_the_defects_both_renderers_show() -> None:
    """``bench render``'s defects column: ours over Cycles' flux with the frames' gain, over the defects Cycles shows
    (a glint under 1e-3 of a full-scale pixel there, or one outside the frame, is left out)."""
    ours = np.array([0.2, 0.4, 0.3, np.nan, 0.1])
    cycles = np.array([0.25, 0.4, 1e-4, 0.3, 0.2])
    found = flux_ratios(ours, cycles, 1.25)
    assert found["defects"] == 3
    assert found["flux_ratio_min"] == pytest.approx(0.625) and found["flux_ratio_max"] == pytest.approx(1.25)
    assert found["flux_ratio_median"] == pytest.approx(1.0)
    assert flux_ratios(np.zeros(0), np.zeros(0), None) == {
        "defects": 0,
        "flux_ratio_median": None,
        "flux_ratio_min": None,
        "flux_ratio_max": None,
    }
    scene = _scene([[0.3 * np.cos(2.0), 0.3 * np.sin(2.0), 0.0, 0.015]])
    shown = glint_fluxes(lambda s, c: Renderer(s, supersample=2).render(c), scene)
    assert shown.shape == (1,) and shown[0] > 0  # the glint outshines the face the sphere hides
