"""What a calibration left open (service/calibration/open_ranges.py) and `meniscope train` over it: the report's
unidentified parameters read back with their ranges, scenes drawn over them within their bounds at the extremes, and
the training's frames and windows rendered from such scenes."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service import DEFAULT_SCENE
from service.calibration import parameters as P
from service.calibration.open_ranges import SCHEMA, beside, drawn_over, open_ranges, report_paths
from service.errors import MeniscopeError
from service.scene import Scene
from tests.servicekit import meniscope

SCENE = Scene.load(DEFAULT_SCENE)
#: Parameters that shape the render, and the sensor's (which the draw leaves to the camera's own draws).
RENDERED = [p for p in P.PARAMETERS if p.rebuild]
SENSOR = [p for p in P.PARAMETERS if not p.rebuild]


def _report(scene: Scene, rows: list[dict]) -> dict:
    return {"schema": SCHEMA, "scene_sha256": scene.sha256, "parameters": rows}


def test_only_parameters_left_unidentified_with_a_range_of_some_width_are_open() -> None:
    rows = [
        {"name": "fluid.roughness", "identified": False, "range": [0.1, 0.25]},
        {"name": "fluid.reflectance", "identified": True, "range": [0.8, 0.9]},
        {"name": "light.angle_deg", "identified": False, "range": [4.0, 4.0]},
        {"name": "camera.exposure", "identified": False, "range": None},
        {"name": "light.elevation_deg", "identified": False, "range": [-40.7, -37.9]},
    ]
    assert open_ranges(_report(SCENE, rows)) == {"fluid.roughness": (0.1, 0.25), "light.elevation_deg": (-40.7, -37.9)}


def test_the_report_beside_a_scene_counts_only_when_made_for_it(tmp_path: Path) -> None:
    """No report, or one whose scene is not this one (edited since, or written by hand), leaves nothing open; a
    report that is not one is a one-line error naming it."""
    scene_path = tmp_path / "SCENE.json"
    shutil.copy(DEFAULT_SCENE, scene_path)
    report = report_paths(scene_path)[0]
    assert report.name == "SCENE.calibration.json" and beside(scene_path, SCENE) == {}
    row = {"name": "light.angle_deg", "identified": False, "range": [2.0, 8.0]}
    report.write_text(json.dumps(_report(SCENE, [row])))
    assert beside(scene_path, SCENE) == {"light.angle_deg": (2.0, 8.0)}
    other = SCENE.model_copy(update={"fluid": SCENE.fluid.model_copy(update={"roughness": 0.2})})
    assert beside(scene_path, Scene.from_dict(other.as_dict())) == {}
    for text in ("{not json", json.dumps({"schema": "other/1"})):
        report.write_text(text)
        with pytest.raises(MeniscopeError, match="not a calibration report") as err:
            beside(scene_path, SCENE)
        assert str(report) in str(err.value) and "\n" not in str(err.value)


def _span(p: P.Parameter, lo_frac: float, hi_frac: float) -> tuple[float, float]:
    """A range inside the parameter's bounds (fractions of them, in its fitted coordinate)."""
    lo, hi = p.to_fit(p.low), p.to_fit(p.high)
    if p.span is not None:  # angles: around the default scene's value
        value = float(SCENE.as_dict()[p.path[0]][p.path[1]])
        lo, hi = value - p.span, value + p.span
    a, b = sorted((lo_frac, hi_frac))
    return p.from_fit(lo + a * (hi - lo)), p.from_fit(lo + b * (hi - lo))


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    names=st.sets(st.sampled_from([p.name for p in P.PARAMETERS]), min_size=1),
    lo=st.sampled_from([0.0, 1e-9, 0.3, 1.0]),
    hi=st.sampled_from([0.0, 0.5, 1.0 - 1e-9, 1.0]),
)
def test_a_scene_drawn_over_open_ranges_stays_in_them_and_keeps_everything_else(
    seed: int, names: set[str], lo: float, hi: float
) -> None:
    """Each open parameter that shapes the render lands inside its range (a range of no width: on it) and the scene
    still validates, at the parameters' own bounds; everything else (geometry, defects, the sensor's values, which
    the camera's own draws cover) is the scene's; the same seed draws the same scene."""
    ranges = {name: _span(P.PARAMETERS[P.index(name)], lo, hi) for name in names}
    out = drawn_over(SCENE, ranges, np.random.default_rng(seed))
    assert Scene.model_validate(out.model_dump()) == out == drawn_over(SCENE, ranges, np.random.default_rng(seed))
    before, after = SCENE.as_dict(), out.as_dict()
    for p in P.PARAMETERS:
        section, key = p.path
        if p in RENDERED and p.name in ranges:
            low, high = ranges[p.name]
            value = after[section][key]
            slack = 1e-12 * max(1.0, abs(low), abs(high))  # the log coordinate's round trip
            assert math.isfinite(value) and low - slack <= value <= high + slack
            before[section][key] = value
    assert after == before  # nothing else moved, the sensor (absent here) not added
    assert "sensor" not in after


def test_no_open_range_draws_nothing() -> None:
    """With nothing open the scene comes back as it is and the generator is untouched (datasets stay the same)."""
    rng = np.random.default_rng(3)
    assert drawn_over(SCENE, {}, rng) is SCENE
    assert drawn_over(SCENE, {p.name: (0.0, 0.01) for p in SENSOR}, rng) is SCENE
    assert rng.random() == np.random.default_rng(3).random()


@pytest.mark.slow
def test_train_renders_over_the_open_ranges_of_the_report_beside_its_scene(tmp_path: Path) -> None:
    """`meniscope train --scene S --open-ranges` with S.calibration.json beside it (made for S) says what it trains
    over, keeps it in the dataset's jitter and the window model's record; a broken report stops it in one line."""
    pytest.importorskip("torch", reason="training needs the train extra (torch)")
    scene_path, lab = tmp_path / "S.json", tmp_path / "lab.cine"
    shutil.copy(DEFAULT_SCENE, scene_path)
    rows = [
        {"name": "light.angle_deg", "identified": False, "range": [2.0, 8.0]},
        {"name": "fluid.reflectance", "identified": True, "range": [0.8, 0.95]},
    ]
    report = report_paths(scene_path)[0]
    report.write_text(json.dumps(_report(SCENE, rows)))
    done = meniscope("simulate", "--out", str(lab), "--windows", "3", "--seed", "1")
    assert done.returncode == 0, done.stderr
    args = ("train", "--scene", str(scene_path), "--lab-video", str(lab), "--quick", "--open-ranges", "--out")
    done = meniscope(*args, str(tmp_path / "m"))
    assert done.returncode == 0, done.stderr
    assert "rendering over what the calibration left open: light.angle_deg 2-8\n" in done.stdout
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert manifest["training"]["config"]["open_ranges"] == {"light.angle_deg": [2.0, 8.0]}
    assert json.loads((tmp_path / "m" / "window.json").read_text())["open_ranges"] == {"light.angle_deg": [2.0, 8.0]}
    report.write_text("{")
    done = meniscope(*args, str(tmp_path / "m2"))
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "S.calibration.json" in done.stderr


def test_a_dataset_for_a_calibrated_scene_is_rendered_over_its_open_ranges(tmp_path: Path) -> None:
    """`meniscope dataset --open-ranges` reads the report beside its scene as `train` does and keeps the ranges in
    its manifest; by default it renders at the calibrated values."""
    scene_path = tmp_path / "S.json"
    shutil.copy(DEFAULT_SCENE, scene_path)
    row = {"name": "fluid.roughness", "identified": False, "range": [0.03, 0.12]}
    report_paths(scene_path)[0].write_text(json.dumps(_report(SCENE, [row])))
    for flags, expected in ((["--open-ranges"], {"fluid.roughness": [0.03, 0.12]}), ([], {})):
        out = tmp_path / f"d{len(flags)}"
        done = meniscope("dataset", "--scene", str(scene_path), "--samples", "64", "--out", str(out), *flags)
        assert done.returncode == 0, done.stderr
        assert ("left open: fluid.roughness 0.03-0.12" in done.stdout) == bool(expected)
        manifest = json.loads((out / "manifest.json").read_text())
        assert manifest["config"]["jitter"]["open_ranges"] == expected
