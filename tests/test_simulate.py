"""Synthetic recordings: ejections on schedule, motion drawn from physical ranges, a truth sidecar
that reproduces every frame, files any reader opens, the same bytes for the same seed."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from service.camera_effects import CameraEffects, noise_preset
from service.cli import main
from service.errors import MeniscopeError
from service.physics import CoefficientRanges, WindowMotion
from service.recordings import open_recording
from service.render import Renderer
from service.scene import Scene
from service.simulate import (
    SCHEMA,
    Transient,
    WindowRanges,
    ejection_frames,
    plan_recording,
    simulate,
    truth_path,
)

WINDOWS = 3


@pytest.fixture(scope="module")
def renderer(scene: Scene) -> Renderer:
    return Renderer(scene)


@pytest.fixture(scope="module")
def ideal(scene: Scene, renderer: Renderer, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """A noise-free 12-bit recording of three windows and its truth."""
    out = tmp_path_factory.mktemp("ideal") / "rec.cine"
    return out, simulate(scene, out, windows=WINDOWS, seed=3, effects=CameraEffects(bit_depth=12), renderer=renderer)


@pytest.fixture(scope="module")
def lab(scene: Scene, renderer: Renderer, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same motion through the "lab" camera, 8 bits."""
    out = tmp_path_factory.mktemp("lab") / "rec.cine"
    simulate(scene, out, windows=WINDOWS, seed=3, effects=noise_preset("lab", 8), noise="lab", renderer=renderer)
    return out


def frames_of(path: Path) -> np.ndarray:
    rec = open_recording(path)
    return rec.read(0, rec.frame_count)


def coefficients_from_truth(truth: dict) -> np.ndarray:
    """(frames, 4) d, p, a, b rebuilt from the sidecar alone, as its documentation says."""
    fps, n_transient = truth["recording"]["fps"], truth["transient"]["frames"]
    rows = []
    for w in truth["windows"]:
        i = np.arange(w["end_frame"] - w["start_frame"])
        coeffs = WindowMotion(**w["truth"]).coefficients(i / fps).to_array()
        bulge = i < n_transient
        coeffs[bulge, 2] += w["bulge_mm"] * np.sin(np.pi * (i[bulge] + 0.5) / n_transient)
        rows.append(coeffs)
    return np.concatenate(rows)


def test_ejections_fall_every_period_rounded_to_the_nearest_frame() -> None:
    assert list(ejection_frames(3, 19000, 100)) == [0, 190, 380, 570]
    uneven = ejection_frames(4, 19001, 100)  # 190.01 frames apart
    assert list(uneven) == [0, 190, 380, 570, 760]
    assert list(ejection_frames(3, 1000, 300)) == [0, 3, 7, 10]  # 3.33 frames: windows of 3, 4, 3


def test_default_window_ranges_stay_where_the_models_are_trained() -> None:
    ranges, coeffs = WindowRanges(), CoefficientRanges()
    assert coeffs.d[0] <= ranges.d[0] and ranges.d[1] <= coeffs.d[1]
    assert coeffs.p[0] <= ranges.p[0] and ranges.p[1] <= coeffs.p[1]
    assert ranges.A1[1] <= coeffs.a[1] and ranges.A2[1] <= coeffs.b[1]


def test_drawn_motion_is_physical() -> None:
    rng = np.random.default_rng(0)
    ranges = WindowRanges().for_fps(19000)
    for truth in (ranges.sample(rng) for _ in range(500)):
        assert 100 <= truth.g1 < truth.g2 <= 3000, "mode 2 decays faster, 100-3000 /s"
        assert 2.2 <= truth.f2 / truth.f1 <= 2.4 and 500 <= truth.f1 and truth.f2 <= 0.35 * 19000
        assert 0.010 <= truth.A1 <= 0.025 and 0.003 <= truth.A2 <= 0.012
        assert 0 <= truth.phi1 < 2 * math.pi and 0 <= truth.phi2 < 2 * math.pi


def test_a_slow_camera_lowers_the_frequencies_or_refuses() -> None:
    assert WindowRanges().for_fps(8000).f1 == pytest.approx((500.0, 0.35 * 8000 / 2.4))
    with pytest.raises(ValueError, match="cannot sample mode 2"):
        WindowRanges().for_fps(3000)


def test_the_transient_bulges_out_then_the_truth_holds_alone() -> None:
    plan = plan_recording(2, 19000, 100, np.random.default_rng(1))
    assert plan.transient_frames == 5 == Transient().frames(19000)
    coeffs = plan.coefficients(1, 0, 190)
    t = np.arange(190) / 19000
    pure = plan.truths[1].coefficients(t).to_array()
    assert np.array_equal(coeffs[5:], pure[5:])
    extra = coeffs[:5, 2] - pure[:5, 2]
    assert np.allclose(extra, plan.bulges_mm[1] * np.sin(np.pi * (np.arange(5) + 0.5) / 5), rtol=0, atol=1e-15)
    assert extra.argmax() == 2 and extra.max() == pytest.approx(plan.bulges_mm[1])
    assert 0.06 <= plan.bulges_mm[1] <= 0.10
    assert np.array_equal(plan.coefficients(1, 100, 150), coeffs[100:150])


def test_windows_too_short_for_the_transient_are_refused() -> None:
    with pytest.raises(ValueError, match="lower the ejection rate"):
        plan_recording(2, 19000, 1500, np.random.default_rng(0))


def test_the_refusal_does_not_depend_on_how_many_windows_are_drawn() -> None:
    """An ejection every 14.6 frames makes windows of 15 and 14: too short for 5 + 10, even when no 14 is drawn."""
    hz = 19000 / 14.6
    assert list(np.diff(ejection_frames(2, 19000, hz))) == [15, 14]
    for windows in (1, 2):
        with pytest.raises(ValueError, match="lower the ejection rate"):
            plan_recording(windows, 19000, hz, np.random.default_rng(0))


def test_a_plan_from_a_later_window_continues_the_schedule(scene: Scene) -> None:
    whole = ejection_frames(6, 19000, 300)  # 63.33 frames apart: windows of 63 and 64
    assert list(ejection_frames(2, 19000, 300, first=4)) == list(whole[4:])
    plan = plan_recording(2, 19000, 300, np.random.default_rng(0), first_window=4)
    window = plan.window_truth(1, scene.nozzle.radius_mm)
    assert (window["index"], window["start_frame"], window["end_frame"]) == (5, whole[5], whole[6])
    assert window["oscillation_start_frame"] == whole[5] + 5
    t = np.arange(whole[6] - whole[5]) / 19000  # the window's own time: from its ejection
    assert np.array_equal(plan.coefficients(1, 10, 20), plan.truths[1].coefficients(t).to_array()[10:20])


def test_the_sidecar_describes_the_recording(scene: Scene, ideal: tuple[Path, dict]) -> None:
    out, truth = ideal
    assert truth_path(out) == out.with_name("rec.truth.json")
    assert json.loads(truth_path(out).read_text()) == truth
    assert truth["schema"] == SCHEMA and truth["seed"] == 3 and truth["ejection_hz"] == 100.0
    assert truth["scene"] == scene.as_dict() and truth["scene_sha256"] == scene.sha256
    assert truth["recording"] == {
        "path": "rec.cine",
        "frames": 570,
        "fps": 19000.0,
        "width": 96,
        "height": 96,
        "bit_depth": 12,
    }
    assert truth["ejections"] == [0, 190, 380]
    assert [(w["start_frame"], w["end_frame"], w["oscillation_start_frame"]) for w in truth["windows"]] == [
        (0, 190, 5),
        (190, 380, 195),
        (380, 570, 385),
    ]
    assert truth["camera_effects"] == CameraEffects(bit_depth=12).model_dump(mode="json")
    for w in truth["windows"]:
        assert set(w["truth"]) == {"d", "p", "A1", "g1", "f1", "phi1", "A2", "g2", "f2", "phi2"}
        assert w["offset_mm"] == pytest.approx(w["truth"]["d"] + w["truth"]["p"] * scene.nozzle.radius_mm)


def test_the_recording_opens_with_the_scene_rate_and_depth(ideal: tuple[Path, dict]) -> None:
    rec = open_recording(ideal[0])
    assert (rec.frame_count, rec.fps, rec.width, rec.height, rec.bit_depth) == (570, 19000.0, 96, 96, 12)
    assert rec.dtype == np.uint16


def test_the_truth_reproduces_every_frame(ideal: tuple[Path, dict], renderer: Renderer) -> None:
    out, truth = ideal
    coeffs = coefficients_from_truth(truth)
    expected = CameraEffects(bit_depth=12).apply(renderer.render(coeffs), np.random.default_rng())
    assert np.array_equal(frames_of(out), expected)
    # one frame off in time, the same truth no longer fits: the check above can fail
    shifted = CameraEffects(bit_depth=12).apply(renderer.render(np.roll(coeffs, 1, axis=0)), np.random.default_rng())
    assert not np.array_equal(frames_of(out), shifted)


def test_the_ejections_stand_out_in_the_video(ideal: tuple[Path, dict]) -> None:
    frames = frames_of(ideal[0]).astype(np.float64)
    change = np.abs(np.diff(frames, axis=0)).mean(axis=(1, 2))  # change[i]: frame i -> i + 1
    for start in ideal[1]["ejections"]:
        transient = change[start : start + 4].max()
        later = change[start + 20 : start + 190 - 1].max()
        assert transient > 2 * later, f"ejection at frame {start} is not visible"


def test_noise_does_not_hide_the_motion(ideal: tuple[Path, dict], lab: Path) -> None:
    clean = frames_of(ideal[0]).astype(np.float64) / 4095
    noisy = frames_of(lab).astype(np.float64) / 255
    assert frames_of(lab).dtype == np.uint8
    assert 0 < np.abs(noisy - clean).mean() < 0.05
    flat = lambda x: (x - x.mean(axis=0)).reshape(len(x), -1)
    r = np.corrcoef(flat(clean).ravel(), flat(noisy).ravel())[0, 1]
    assert r > 0.9


def test_the_same_seed_gives_the_same_recording(scene: Scene, renderer: Renderer, lab: Path, tmp_path: Path) -> None:
    again = tmp_path / "again.cine"
    simulate(scene, again, windows=WINDOWS, seed=3, effects=noise_preset("lab", 8), noise="lab", renderer=renderer)
    assert np.array_equal(frames_of(again), frames_of(lab))
    other = tmp_path / "other.cine"
    truth = simulate(scene, other, windows=1, seed=4, effects=noise_preset("lab", 8), renderer=renderer)
    assert truth["windows"][0]["truth"] != json.loads(truth_path(lab).read_text())["windows"][0]["truth"]


def test_an_avi_recording_is_8_bit(scene: Scene, renderer: Renderer, tmp_path: Path) -> None:
    out = tmp_path / "rec.avi"
    simulate(scene, out, windows=1, seed=0, effects=noise_preset("low", 8), renderer=renderer)
    rec = open_recording(out)
    assert (rec.frame_count, rec.bit_depth, rec.dtype) == (190, 8, np.uint8)
    assert truth_path(out).is_file()


@pytest.mark.parametrize(
    "name, bit_depth, message",
    [
        ("rec.mp4", 8, "unknown recording format '.mp4': use .cine or .avi"),
        ("rec", 8, "unknown recording format '(none)'"),
        ("rec.avi", 12, ".avi stores bit depths [8], not 12"),
        ("missing/rec.cine", 12, "does not exist"),
    ],
)
def test_unusable_outputs_are_refused_before_rendering(
    scene: Scene, tmp_path: Path, name: str, bit_depth: int, message: str
) -> None:
    with pytest.raises(MeniscopeError, match=re.escape(message)):
        simulate(
            scene, tmp_path / name, windows=1, seed=0, effects=CameraEffects(bit_depth=bit_depth), renderer=object()
        )


def test_the_verb_writes_a_recording_and_its_truth(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "cli.cine"
    assert main(["simulate", "--out", str(out), "--windows", "1", "--seed", "2", "--noise", "none"]) == 0
    assert "190 frames at 19000 fps, 1 windows" in capsys.readouterr().out
    truth = json.loads(truth_path(out).read_text())
    assert truth["noise"] == "none" and truth["recording"]["bit_depth"] == 12


def test_the_verb_draws_the_sun_as_finely_as_asked(scene: Scene, tmp_path: Path) -> None:
    """``--sun-samples 24`` draws the sun's disc as ``calibrate``'s renders do: the frames are those of our renderer
    at 24 directions (noise off, the same seed), not the default's 4, and the truth says how it was drawn."""
    out = tmp_path / "fine.cine"
    argv = ["simulate", "--out", str(out), "--windows", "1", "--seed", "4", "--noise", "none", "--sun-samples", "24"]
    assert main(argv) == 0
    truth = json.loads(truth_path(out).read_text())
    assert truth["sun_samples"] == 24 and truth["renderer"] == "Renderer"
    effects = noise_preset("none", 12)
    for samples, name in ((24, "same.cine"), (4, "coarse.cine")):
        simulate(
            scene, tmp_path / name, windows=1, seed=4, effects=effects, renderer=Renderer(scene, sun_samples=samples)
        )
    fine, same, coarse = (frames_of(tmp_path / name) for name in ("fine.cine", "same.cine", "coarse.cine"))
    assert np.array_equal(fine, same) and not np.array_equal(fine, coarse)
    assert json.loads(truth_path(tmp_path / "coarse.cine").read_text())["sun_samples"] == 4


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--windows", "0"], "--windows: must be at least 1"),
        (["--ejection-hz", "nan"], "--ejection-hz: must be a positive number"),
        (["--bit-depth", "10"], ".cine stores bit depths [8, 12, 16], not 10"),
        (["--scene", "no-such-scene.json"], "no-such-scene.json: scene file not found"),
        (["--sun-samples", "0"], "--sun-samples: must be 1 to 64, got 0"),
        (["--sun-samples", "8", "--renderer", "blender"], "--sun-samples: is our renderer's"),
    ],
)
def test_the_verb_reports_bad_input_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, argv: list[str], message: str
) -> None:
    assert main(["simulate", "--out", str(tmp_path / "x.cine"), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not (tmp_path / "x.cine").exists()


@pytest.mark.skipif(shutil.which("blender") is None, reason="blender not on PATH (Debian: apt install blender)")
def test_the_verb_can_render_with_blender_as_a_second_renderer(
    tmp_path: Path, scene: Scene, capsys: pytest.CaptureFixture
) -> None:
    """A 16-frame window (5 of transient, 11 of oscillation) through Cycles: the truth names the renderer,
    and the frames show the same scene as ours without being ours."""
    out = tmp_path / "cycles.cine"
    argv = [
        "simulate",
        "--out",
        str(out),
        "--renderer",
        "blender",
        "--blender-samples",
        "4",
        "--windows",
        "1",
        "--ejection-hz",
        str(19000 / 16),
        "--noise",
        "none",
        "--seed",
        "3",
    ]
    assert main(argv) == 0
    assert "16 frames" in capsys.readouterr().out
    truth = json.loads(truth_path(out).read_text())
    assert truth["renderer"] == "BlenderRenderer"
    simulate(scene, tmp_path / "ours.cine", windows=1, seed=3, ejection_hz=19000 / 16, effects=noise_preset("none", 12))
    with open_recording(out) as rec, open_recording(tmp_path / "ours.cine") as other:
        cycles, ours = np.asarray(rec.read(0, 16), np.float64), np.asarray(other.read(0, 16), np.float64)
    assert not np.array_equal(cycles, ours)
    assert np.corrcoef(cycles.ravel(), ours.ravel())[0, 1] > 0.8
