"""The defects' glints: looked for where the lab's pixels are still, found where they are, placed on the face."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service import DEFAULT_SCENE
from service.calibration.artifacts import (
    CONTRAST,
    OUTLINE_PX,
    detect,
    face_pixels,
    glint_positions,
    pixel_ray,
    place,
    still_pixels,
    with_spheres,
)
from service.calibration.fit import SCHEDULE, _moving, _spheres, crop, motion_only
from service.calibration.footage import read_footage
from service.calibration.noise import NoiseFit, fit_noise
from service.calibration.synthesis import Synthesis
from service.camera_effects import CameraEffects
from service.scene import Scene
from service.simulate import simulate

FULL_SCALE = 4095.0


def _speck(shape: tuple[int, int], col: float, row: float, peak: float, sigma: float = 0.8) -> np.ndarray:
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    return peak * np.exp(-((cols - col) ** 2 + (rows - row) ** 2) / (2 * sigma**2))


@settings(max_examples=40, deadline=None)
@given(
    st.floats(0.005, 0.9),
    st.floats(2000.0, 60000.0),
    st.floats(0.0, 20.0),
    st.floats(0.0, 0.2),
    st.integers(0, 2**31 - 1),
)
def test_a_pixel_is_still_unless_something_moves_over_it_most_of_the_time(
    level: float, full_well: float, read_e: float, covered: float, seed: int
) -> None:
    """Noise alone, or a fluid over the pixel in up to a fifth of the frames: still. A highlight over it half the
    time: not still."""
    noise = NoiseFit(full_well, read_e, read_e / full_well, 1, 1.0)
    rng = np.random.default_rng(seed)
    sigma = noise.sigma(np.array(level), FULL_SCALE)
    stack = level + sigma * rng.standard_normal((120, 1, 2))
    stack[: int(covered * 120), 0, 0] += 0.5  # a highlight passing now and then
    stack[::2, 0, 1] += 10 * sigma + 0.5 * level  # one there every other frame
    assert still_pixels(stack, noise, 0.0, FULL_SCALE).tolist() == [[True, False]]


@settings(max_examples=40, deadline=None)
@given(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(0.01, 0.3), st.floats(0.1, 1.0), st.integers(2, 3))
def test_a_glint_beside_a_dark_leftover_is_found_where_it_is(
    dx: float, dy: float, peak: float, dark: float, gap: int
) -> None:
    """A speck a few pixels from where the model is far brighter than the lab (the fluid's edge) is found within
    0.25 px of its centre, and nowhere else."""
    col, row = 20 + dx, 20 + dy
    residual = _speck((40, 40), col, row, peak)
    residual[20 + gap :, :] -= dark  # the dark leftover below it
    found = detect(residual, np.ones((40, 40), bool), 1e-4, np.zeros((40, 40)))
    assert len(found) == 1
    assert np.hypot(found[0, 0] - col, found[0, 1] - row) < 0.25


@settings(max_examples=30, deadline=None)
@given(st.floats(0.01, 0.3), st.floats(0.05, 0.95).filter(lambda f: abs(f - CONTRAST) > 0.02))
def test_a_speck_is_a_glint_only_against_the_face_it_lies_on(level: float, fraction: float) -> None:
    """Against a face of ``level``, a speck is a glint only above CONTRAST of it (where two renderers draw the
    face's edges, their leftovers are fainter)."""
    residual = _speck((30, 30), 15, 15, fraction * level)
    found = detect(residual, np.ones((30, 30), bool), 1e-4, np.full((30, 30), level))
    assert len(found) == (1 if fraction > CONTRAST else 0)


@settings(max_examples=30, deadline=None)
@given(st.floats(0.0, 2.0), st.floats(0.5, 1.0), st.floats(3.2, 8.0))
def test_one_glint_is_found_once_and_two_apart_twice(apart: float, second: float, far: float) -> None:
    """Two maxima within one flux square (a broad highlight's ripple, or a tie) are one glint; glints further apart
    than the square are two."""
    one = _speck((30, 30), 12, 15, 0.1) + _speck((30, 30), 12 + apart, 15, second * 0.1)
    two = _speck((30, 30), 12, 15, 0.1) + _speck((30, 30), 12 + far, 15, second * 0.1)
    assert len(detect(one, np.ones((30, 30), bool), 1e-4, np.zeros((30, 30)))) == 1
    assert len(detect(two, np.ones((30, 30), bool), 1e-4, np.zeros((30, 30)))) == 2


@settings(max_examples=20, deadline=None)
@given(st.floats(-70.0, -15.0), st.floats(0.4, 1.2), st.integers(40, 120))
def test_glints_are_looked_for_on_the_face_and_not_by_its_outline(elevation: float, fov: float, size: int) -> None:
    """Every pixel looked at sees the face (bore radius < r < outer radius), and so do its neighbours up to
    OUTLINE_PX away; the face's inner part, by the bore, is looked at."""
    data = json.loads(Path(DEFAULT_SCENE).read_text())
    data["camera"].update(elevation_deg=elevation, fov_deg=fov, width_px=size, height_px=size)
    scene = Scene.from_dict(data)
    mask = face_pixels(scene)
    rows, cols = np.mgrid[0:size, 0:size]
    location, d = pixel_ray(scene, cols.ravel().astype(float), rows.ravel().astype(float))
    r = np.hypot(*(location[:2, None] + (-location[2] / d[..., 2]) * d[..., :2].T)).reshape(size, size)
    near = cv2.dilate(mask.astype(np.uint8), np.ones((2 * OUTLINE_PX + 1,) * 2, np.uint8)).astype(bool)
    assert (r[near] < scene.nozzle.outer_radius_mm).all() and (r[mask] > scene.nozzle.radius_mm).all()
    rim = (r > scene.nozzle.radius_mm) & (r < 1.2 * scene.nozzle.radius_mm)
    assert mask[rim].any()


@settings(max_examples=30, deadline=None)
@given(st.floats(0.0, 2 * np.pi), st.floats(0.26, 0.6), st.floats(0.004, 0.03), st.floats(150.0, 210.0))
def test_a_sphere_is_placed_back_from_its_glint(azimuth: float, ring: float, radius: float, light_az: float) -> None:
    """The half-vector placement inverts the glint's projection for any sphere on the face seen by the camera (to
    1e-5 mm, a thousandth of a pixel: the scoring takes the view from the sphere's centre, the placement from the
    glint)."""
    data = json.loads(Path(DEFAULT_SCENE).read_text())
    data["light"]["azimuth_deg"] = light_az
    scene = Scene.from_dict(data)
    sphere = np.array([[ring * np.cos(azimuth), ring * np.sin(azimuth), 0.0, radius]])
    glint = glint_positions(scene, sphere)
    np.testing.assert_allclose(place(scene, glint, sphere[:, 3]), sphere[:, :3], atol=1e-5)


@dataclass(frozen=True)
class Defects:
    """A recording by our renderer of eight rough defects (alpha 0.2) round the bore's rim (none behind the
    meniscus, where the fluid's own highlight hides them), most of them where the fluid can reach in the model, and
    what calibrate has when it looks for them: the true scene without spheres, its static stack, moving pixels and
    noise, and the motion of four fitted frames."""

    true: Scene
    scene: Scene
    synth: Synthesis
    stack: np.ndarray
    moving: np.ndarray
    noise: NoiseFit
    full_scale: float
    lab: np.ndarray
    motion: np.ndarray


@pytest.fixture(scope="module")
def defects(tmp_path_factory: pytest.TempPathFactory) -> Defects:
    data = json.loads(Path(DEFAULT_SCENE).read_text())
    data["camera"].update(width_px=72, height_px=72)
    rim = np.radians([-70, -45, -20, 60, 120, 160, 200, 240])
    spheres = [{"x": 0.3 * np.cos(a), "y": 0.3 * np.sin(a), "z": 0.0, "radius": 0.014} for a in rim]
    data["artifacts"].update(spheres=spheres, material={"roughness": 0.2, "reflectance": 0.9})
    true = Scene.from_dict(data)
    out = tmp_path_factory.mktemp("defects") / "defects.cine"
    camera = CameraEffects(offset=0.01, blur_sigma_px=0.6, full_well_e=16000, read_noise_dn=5.0, bit_depth=12)
    simulate(true, out, windows=2, seed=5, ejection_hz=1000.0, effects=camera)
    footage = read_footage(out, frames=4, stack=60, ejection_hz=1000.0)
    data["sensor"] = {"offset": 0.01, "blur_sigma_px": 0.6}
    scene = with_spheres(Scene.from_dict(data), np.zeros((0, 4)))
    synth = Synthesis(supersample=2)
    stack = crop(footage.stack, scene)
    moving = _moving(synth, scene)
    noise = fit_noise(stack, ~moving, 0.01, footage.full_scale)
    lab = crop(footage.frames, scene)
    motion = motion_only(synth, scene, lab, SCHEDULE[-1].sigmas)
    return Defects(true, scene, synth, stack, moving, noise, footage.full_scale, lab, motion)


def test_glints_by_the_bore_are_found_within_1_px_where_the_fluid_can_reach(defects: Defects) -> None:
    """Every glint of the rough defects is recovered within 1 px, and nothing else is."""
    d = defects
    found = _spheres(d.synth, d.scene, d.stack, d.moving, d.noise, d.full_scale)
    truth = glint_positions(d.true, d.true.spheres)
    cols, rows = np.rint(truth).astype(int).T
    assert d.moving[rows, cols].sum() >= 4  # where the fluid's reach in the model hid them before
    dist = np.linalg.norm(truth[:, None] - glint_positions(d.scene, found)[None], axis=-1)
    assert (dist.min(axis=1) <= 1.0).all()  # every glint is found within 1 px
    assert len(found) == len(truth)  # and nothing else is


def test_the_defects_radii_come_back_from_their_glints_flux(defects: Defects) -> None:
    """A glint is a point source of flux F E r^2 / 4 (service.render.glints), so the radius sized from a glint's
    flux against a render is the sphere's own, whatever its roughness (0.2 here, the guess's 0.06 used): their
    median within 5 %, each within 30 % (noise, blur and the face's own structure in the flux square share it)."""
    d = defects
    found = _spheres(d.synth, d.scene, d.stack, d.moving, d.noise, d.full_scale)
    truth = glint_positions(d.true, d.true.spheres)
    nearest = np.linalg.norm(glint_positions(d.scene, found)[:, None] - truth[None], axis=-1).argmin(axis=1)
    ratio = found[:, 3] / d.true.spheres[nearest, 3]
    assert abs(np.median(ratio) - 1) < 0.05 and (np.abs(ratio - 1) < 0.3).all()
