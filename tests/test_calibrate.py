"""meniscope calibrate: a recording of a known mismatched scene, made by our renderer, is calibrated back."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service import DEFAULT_SCENE
from service.calibration.fit import SCHEDULE, Stage, calibrate
from service.calibration.footage import read_footage
from service.calibration.report import document
from service.camera_effects import CameraEffects
from service.scene import Scene
from service.simulate import simulate

#: A small camera (40 px, coarse pixels) so that the whole calibration takes seconds.
SMALL = {"width_px": 40, "height_px": 40, "fov_deg": 0.6, "roi": [0, 0]}


def _scene(**changes: dict) -> Scene:
    data = json.loads(Path(DEFAULT_SCENE).read_text())
    data["camera"].update(SMALL)
    data["artifacts"]["count"] = 0
    for section, values in changes.items():
        data[section].update(values)
    return Scene.from_dict(data)


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 'lab' recording: the light 5 deg round, a brighter exposure, a black level, shot and read noise, and the
    ROI off the corner of a larger frame."""
    true = _scene(light={"azimuth_deg": 185.0}, camera={"exposure": 1.5, "roi": [5, 3]})
    out = tmp_path_factory.mktemp("lab") / "lab.cine"
    camera = CameraEffects(offset=0.03, blur_sigma_px=0.5, full_well_e=40000, read_noise_dn=1.0, bit_depth=12)
    simulate(true, out, windows=2, seed=4, ejection_hz=1000.0, effects=camera, frame=(48, 46))
    return out


def test_a_known_mismatch_is_recovered(lab: Path) -> None:
    footage = read_footage(lab, frames=8, stack=38)
    quick = tuple(Stage(stage.sigmas, 1, 10) for stage in SCHEDULE)
    cal = calibrate(footage, _scene(), schedule=quick, start_alphas=(), progress=False)
    found = cal.scene
    assert found.camera.roi == (5, 3)
    assert found.light.azimuth_deg == pytest.approx(185.0, abs=1.0)
    assert found.camera.exposure == pytest.approx(1.5, rel=0.15)
    assert found.sensor.offset == pytest.approx(0.03, abs=0.003)
    assert found.sensor.full_well_e == pytest.approx(40000, rel=0.2)
    assert cal.residual_after < 0.7 * cal.residual_before
    doc = document(cal, footage)
    assert doc["versus_truth"]["roi"]["error_px"] == 0
    json.dumps(doc, allow_nan=False)


def test_a_larger_frame_shows_the_scene_around_the_roi() -> None:
    from service.camera_effects import CameraEffects
    from service.render import Renderer
    from service.simulate import CameraFrames, canvas

    scene = _scene(camera={"roi": [5, 2]})
    big, corner = canvas(scene, (50, 47))
    camera = CameraFrames(scene, Renderer(big), CameraEffects(bit_depth=16), (50, 47), corner)
    coeffs = np.array([[0.01, 0.05, 0.01, 0.004]])
    frame = camera.take(coeffs, np.random.default_rng(0)).astype(np.float64) / 65535
    roi = Renderer(scene).render(coeffs)
    np.testing.assert_allclose(frame[:, 2:42, 5:45], roi, atol=2e-5)  # the ROI is the scene's own view
    outside = np.ones(frame.shape[1:], bool)
    outside[2:42, 5:45] = False
    assert frame[0][outside].max() > 0.01  # and the frame around it is the nozzle's face, not black
