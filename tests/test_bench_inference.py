"""`meniscope bench inference`: the learned graphs alone under each setting asked for, as the service runs
them, one row per model folder, method and setting, with each method's fastest marked."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from service import DEFAULT_MODELS
from service.inverse.network import NetworkMethod
from service.pipeline.demo import DEMO_AVI
from service.recordings.roi import read_roi_frames
from service.scene import Scene
from tests.servicekit import meniscope


def test_every_setting_of_every_method_is_measured_once(tmp_path: Path):
    out = tmp_path / "inference.json"
    done = meniscope(
        "bench",
        "inference",
        "--frames",
        "64",
        "--repeats",
        "2",
        "--threads",
        "1,2",
        "--batches",
        "16,64",
        "--optimisation",
        "basic,all",
        "--out",
        out,
    )
    assert done.returncode == 0, done.stderr
    rows = json.loads(out.read_text())["rows"]
    settings = {(r["label"], r["threads"], r["batch"], r["optimisation"]) for r in rows}
    assert len(settings) == len(rows) == 2 * 2 * 2 * 2
    assert {r["label"] for r in rows} == {"network 32px", "direct 32px"}
    assert all(r["frames_per_s"] > 0 for r in rows)
    table = out.with_suffix(".md").read_text()
    assert table.count("(fastest)") == 2 and table.count("| network 32px |") == 8


def test_settings_that_are_not_settings_are_refused_in_one_line(tmp_path: Path):
    for option, value in (("--batches", "0"), ("--threads", "two"), ("--optimisation", "max")):
        done = meniscope("bench", "inference", option, value, "--out", tmp_path / "x.json")
        assert done.returncode == 2 and option in done.stderr and done.stderr.strip().count("\n") <= 1, done.stderr


def test_the_settings_compared_change_the_speed_not_the_answer(scene: Scene):
    frames, _ = read_roi_frames(DEMO_AVI, scene, 32)
    reference = NetworkMethod(DEFAULT_MODELS, scene).infer(frames).coefficients
    for threads, batch, level in ((1, 5, "none"), (2, 16, "basic"), (1, 64, "extended")):
        method = NetworkMethod(DEFAULT_MODELS, scene, threads=threads, batch=batch, optimisation=level)
        np.testing.assert_allclose(method.infer(frames).coefficients, reference, atol=1e-5)
