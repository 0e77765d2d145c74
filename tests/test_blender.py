"""service.render.blender: the Blender Cycles reference backend.

The tests marked ``blender`` run the real executable (skipped when it is not on PATH);
the others check what happens around it: inputs, the job it is given, its failures.
"""

from __future__ import annotations

import json
import shutil
import stat
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from service import DEFAULT_SCENE
from service.errors import MeniscopeError
from service.physics import CoefficientRanges, displacement, slope
from service.render.agreement import highlights
from service.render.blender import BlenderRenderer, camera_frame, fluid_profiles
from service.scene import Scene, direction

needs_blender = pytest.mark.skipif(
    shutil.which("blender") is None, reason="blender not on PATH (Debian: apt install blender)"
)


def example(**changes: dict) -> Scene:
    """The example scene with some sections' keys changed; ``artifacts`` is replaced whole."""
    data = json.loads(DEFAULT_SCENE.read_text())
    for section, values in changes.items():
        data[section] = values if section == "artifacts" else {**data[section], **values}
    return Scene.from_dict(data)


# ---- around Blender: no executable needed ------------------------------------------------


def test_fluid_profiles_sample_eq1_heights_and_slopes_on_the_mesh_rings():
    coeffs = np.array([[0.01, 0.1, 0.02, -0.01], [-0.03, -0.2, 0.0, 0.015]])
    prof = fluid_profiles(coeffs, radius=0.25, rings=8)
    r = 0.25 * np.arange(9) / 8
    assert prof.shape == (2, 2, 9) and prof.dtype == np.float32
    for (d, p, a, b), (z, s) in zip(coeffs, prof):
        np.testing.assert_allclose(z, -displacement(r, d, p, a, b, 0.25), atol=1e-7)
        np.testing.assert_allclose(s, slope(r, p, a, b, 0.25), atol=1e-6)
    np.testing.assert_allclose(prof[:, 0, -1], -coeffs[:, 0], atol=1e-7)  # D(R) = d at the rim


@given(az=st.floats(-720, 720), el=st.floats(-89.9, 89.9))
def test_camera_frame_looks_at_the_origin_with_world_up_projected(az, el):
    scene = example(camera={"azimuth_deg": az, "elevation_deg": el})
    location, forward, up = camera_frame(scene)
    np.testing.assert_allclose(location, scene.camera.distance_mm * direction(az, el), atol=1e-9)
    np.testing.assert_allclose(forward, -location / np.linalg.norm(location), atol=1e-12)
    assert np.linalg.norm(up) == pytest.approx(1.0)
    assert abs(up @ forward) < 1e-9
    assert up[2] > 0  # world +z points up in the image
    assert abs(np.cross(forward, up)[2]) < 1e-9  # image right stays horizontal


def test_job_maps_roughness_to_blenders_square_root_and_lists_the_artifacts():
    scene = example(fluid={"roughness": 0.04, "reflectance": 0.7})
    job = BlenderRenderer(scene).job(5, Path("p.f32"), Path("o.f32"))
    assert job["fluid"] == {"roughness": pytest.approx(0.2), "reflectance": 0.7}
    assert job["spheres"] == scene.spheres.tolist()
    assert job["frames"] == 5 and job["samples"] == 32
    json.dumps(job, allow_nan=False)


def test_zero_frames_render_nothing_and_start_no_blender():
    out = BlenderRenderer(example(), blender="no-such-blender").render(np.zeros((0, 4)))
    assert out.shape == (0, 96, 96) and out.dtype == np.float32


@pytest.mark.parametrize(
    ("coeffs", "problem"),
    [(np.zeros((3, 5)), "shape"), (np.array([[0.0, np.nan, 0.0, 0.0]]), "NaN"), (np.zeros((2, 2, 4)), "shape")],
)
def test_bad_coefficients_are_refused_before_blender_starts(coeffs, problem):
    with pytest.raises(MeniscopeError, match=problem):
        BlenderRenderer(example(), blender="no-such-blender").render(coeffs)


def test_a_missing_blender_is_a_one_line_error_naming_it():
    with pytest.raises(MeniscopeError, match="no-such-blender.*not found"):
        BlenderRenderer(example(), blender="no-such-blender").render(np.zeros((1, 4)))


def test_a_failing_blender_reports_its_own_error_line(tmp_path):
    fake = tmp_path / "blender"
    fake.write_text("#!/bin/sh\necho 'Blender 3.4.1'\necho 'Error: Python: Traceback: boom' >&2\nexit 3\n")
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    with pytest.raises(MeniscopeError, match=r"exit 3.*0 of 2 frames.*boom") as info:
        BlenderRenderer(example(), blender=str(fake), progress=False).render(np.zeros((2, 4)))
    assert "\n" not in str(info.value)


# ---- the real Blender ------------------------------------------------------------------------

#: Two large specular spheres below the outlet, left and right of the fluid, in a
#: 96 x 64 ROI (not square, so a wrong sensor fit shows).
SPHERES = [{"x": 0.0, "y": 0.33, "z": -0.2, "radius": 0.12}, {"x": 0.0, "y": -0.33, "z": -0.2, "radius": 0.12}]


@pytest.fixture(scope="module")
def sphere_scene_frames() -> tuple[Scene, np.ndarray]:
    scene = example(camera={"width_px": 96, "height_px": 64}, artifacts={"spheres": SPHERES})
    coeffs = CoefficientRanges().sample(3, np.random.default_rng(1))
    renderer = BlenderRenderer(scene, samples=16, progress=False)
    frames = renderer.render(coeffs)
    assert renderer.last_timing is not None and renderer.last_timing.frame_s.shape == (3,)
    return scene, frames


@needs_blender
@pytest.mark.blender
@pytest.mark.slow
def test_frames_are_float32_in_the_unit_range_one_per_coefficient_row(sphere_scene_frames):
    _, frames = sphere_scene_frames
    assert frames.shape == (3, 64, 96) and frames.dtype == np.float32
    assert 0.0 <= frames.min() and frames.max() <= 1.0


@needs_blender
@pytest.mark.blender
@pytest.mark.slow
def test_sphere_highlights_land_where_project_puts_the_mirror_point(sphere_scene_frames):
    """The sun's glint on a sphere sits where its normal halves light and view directions."""
    from service.render import project

    scene, frames = sphere_scene_frames
    light = direction(scene.light.azimuth_deg, scene.light.elevation_deg)
    camera, _, _ = camera_frame(scene)
    for x, y, z, radius in scene.spheres:
        centre = np.array([x, y, z])
        view = (camera - centre) / np.linalg.norm(camera - centre)
        half = (light + view) / np.linalg.norm(light + view)
        col, row = project(scene, centre + radius * half)
        c, r = int(round(col)), int(round(row))
        window = frames[:, r - 5 : r + 6, c - 5 : c + 6]  # the glint only, not the sphere's other reflections
        found = highlights(window, threshold=0.1)
        assert found.found.all()
        measured = found.centroid + [c - 5, r - 5]
        np.testing.assert_allclose(measured, np.tile([col, row], (3, 1)), atol=0.3)


@needs_blender
@pytest.mark.blender
@pytest.mark.slow
def test_nozzle_face_is_lambertian_under_the_suns_irradiance(sphere_scene_frames):
    """Radiance of the bottom face = albedo * strength * cos(incidence) / pi, read back linear."""
    from service.render import project

    scene, frames = sphere_scene_frames
    light = direction(scene.light.azimuth_deg, scene.light.elevation_deg)
    expected = scene.nozzle.albedo * scene.light.strength * max(0.0, -light[2]) / np.pi * scene.camera.exposure
    col, row = np.round(project(scene, np.array([-0.45, 0.0, 0.0]))).astype(int)  # far side of the face
    patch = frames[:, row - 2 : row + 3, col - 3 : col + 4]
    assert np.median(patch) == pytest.approx(expected, rel=0.03)
