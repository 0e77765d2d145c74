"""``meniscope train`` end to end (quick settings): ONNX graphs that match torch, a manifest that guards
them, the run-time method that loads them, and one-line errors for what users get wrong."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from service.errors import MeniscopeError
from service.inverse import window_model as wm
from service.inverse.manifest import MANIFEST, load_manifest
from service.inverse.network import NetworkMethod
from service.recordings import open_recording
from service.scene import Scene
from service.validation.report import lab_frames, reconstructions, validate
from tests.servicekit import meniscope

pytest.importorskip("torch", reason="training needs the train extra (torch)")

#: The export's promise: onnxruntime and torch agree on every output within this (mm).
PARITY_MM = 1e-4


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """A lab video, a hold-out recording and the model folder quick training made from them."""
    folder = tmp_path_factory.mktemp("train")
    lab, holdout, models = folder / "lab.cine", folder / "holdout.avi", folder / "models"
    for rec, seed, windows in ((lab, 1, 3), (holdout, 2, 2)):
        done = meniscope("simulate", "--out", str(rec), "--windows", str(windows), "--seed", str(seed))
        assert done.returncode == 0, done.stderr
    done = meniscope("train", "--lab-video", str(lab), "--holdout", str(holdout), "--out", str(models), "--quick")
    assert done.returncode == 0, done.stderr
    assert "network on recording" in done.stdout and "direct on synthetic" in done.stdout
    return lab, holdout, models


def test_train_exports_both_methods_with_a_manifest_and_plots(trained: tuple[Path, Path, Path], scene: Scene) -> None:
    _, _, models = trained
    manifest = load_manifest(models, scene)
    assert set(manifest.methods) == {"network", "direct"}
    for name in ("network.onnx", "direct.onnx", "autoencoder.onnx", "losses.png", "validation.png"):
        assert (models / name).stat().st_size > 0
    assert set(manifest.validation["network"]) == {"synthetic", "recording"}
    for entry in (*manifest.methods.values(), manifest.autoencoder):
        assert entry.parity_max_abs <= PARITY_MM
    assert manifest.autoencoder.file == "autoencoder.onnx" and "autoencoder" not in manifest.methods


def test_train_builds_the_window_model_of_its_network_too(trained: tuple[Path, Path, Path], scene: Scene) -> None:
    """The default method (the network and the window model) comes out of one ``train``: the window model reads
    this folder's network, and the manifest lists its files."""
    _, _, models = trained
    manifest = load_manifest(models, scene)
    assert {wm.FILE, wm.RECORD} <= set(manifest.files)
    model = wm.WindowModel.of_folder(models)
    assert model.intervals is None  # --quick leaves the calibration out: the fit's own intervals stay


def test_validate_shows_lab_frames_beside_their_vae_reconstructions(
    trained: tuple[Path, Path, Path], scene: Scene, tmp_path: Path
) -> None:
    """The exported autoencoder graph reproduces what the VAE saw: its ``normalised`` output is the
    pooled, standardised frame, and the reconstruction figure is drawn from it."""
    lab, holdout, models = trained
    frames = lab_frames(lab, scene, count=4)
    shown, recon = reconstructions(models, load_manifest(models, scene), frames)
    assert shown.shape == recon.shape == (4, 32, 32)
    pooled = frames.astype(np.float64).reshape(4, 32, 3, 32, 3).mean(axis=(2, 4))
    expected = (pooled - pooled.mean(axis=(1, 2), keepdims=True)) / pooled.std(axis=(1, 2), ddof=1, keepdims=True)
    np.testing.assert_allclose(shown, expected, atol=1e-3)
    document = validate(scene, models, [], [holdout], tmp_path, lab_video=lab)
    assert (tmp_path / document["figures"]["reconstructions"]).stat().st_size > 10_000


def test_the_runtime_method_infers_raw_frames_of_any_batch_size(trained: tuple[Path, Path, Path], scene: Scene) -> None:
    _, holdout, models = trained
    with open_recording(holdout) as rec:
        frames = np.asarray(rec.read(0, 37))  # uint8 as stored
    for name in ("network", "direct"):
        method = NetworkMethod(models, scene, name, threads=1, batch=16)
        out = method.infer(frames)
        assert out.coefficients.shape == (37, 4) and out.centre.shape == (37,)
        assert np.all(np.isfinite(out.coefficients)) and np.all(np.isfinite(out.centre))
        # batching does not change the answer
        np.testing.assert_allclose(method.infer(frames[:5]).centre, out.centre[:5], atol=1e-6)


def test_a_model_for_another_scene_is_refused(trained: tuple[Path, Path, Path], scene: Scene) -> None:
    data = scene.model_dump()
    data["camera"]["elevation_deg"] = -30.0
    with pytest.raises(MeniscopeError, match="trained for scene"):
        NetworkMethod(trained[2], Scene.from_dict(data))


def test_a_changed_model_file_is_refused(trained: tuple[Path, Path, Path], scene: Scene, tmp_path: Path) -> None:
    copy = tmp_path / "models"
    shutil.copytree(trained[2], copy)
    with (copy / "direct.onnx").open("ab") as fh:
        fh.write(b"\0")
    with pytest.raises(MeniscopeError, match="sha256 differs"):
        NetworkMethod(copy, scene, "direct")
    (copy / MANIFEST).write_text(json.dumps({"schema": "something else"}))
    with pytest.raises(MeniscopeError, match="schema"):
        NetworkMethod(copy, scene)


def test_frames_of_the_wrong_size_or_type_are_a_clear_error(trained: tuple[Path, Path, Path], scene: Scene) -> None:
    method = NetworkMethod(trained[2], scene)
    with pytest.raises(MeniscopeError, match="ROI"):
        method.infer(np.zeros((2, 10, 10), np.uint8))
    with pytest.raises(MeniscopeError, match="pixel type"):
        method.infer(np.zeros((2, scene.camera.height_px, scene.camera.width_px), np.float32))


def test_the_model_input_size_is_a_choice(trained: tuple[Path, Path, Path], scene: Scene, tmp_path: Path) -> None:
    """--input-px sets the pooled image the networks see; the graphs still take the ROI as stored."""
    lab, holdout, _ = trained
    done = meniscope("train", "--lab-video", str(lab), "--out", str(tmp_path / "m16"), "--quick", "--input-px", "16")
    assert done.returncode == 0, done.stderr
    manifest = load_manifest(tmp_path / "m16", scene)
    assert (manifest.input.downsample, manifest.input.model_height, manifest.input.model_width) == (6, 16, 16)
    assert manifest.training.config["net"]["input_px"] == 16
    with open_recording(holdout) as rec:
        assert NetworkMethod(tmp_path / "m16", scene).infer(np.asarray(rec.read(0, 3))).centre.shape == (3,)


def test_the_trunks_channels_are_a_choice(trained: tuple[Path, Path, Path], scene: Scene, tmp_path: Path) -> None:
    """--channels sets the convolutions' widths (a cheaper graph per frame); a warm start keeps its folder's."""
    lab, holdout, _ = trained
    out = tmp_path / "narrow"
    done = meniscope("train", "--lab-video", str(lab), "--out", str(out), "--quick", "--channels", "4,8,8")
    assert done.returncode == 0, done.stderr
    assert load_manifest(out, scene).training.config["net"]["channels"] == [4, 8, 8]
    with open_recording(holdout) as rec:
        assert NetworkMethod(out, scene).infer(np.asarray(rec.read(0, 3))).centre.shape == (3,)
    tuned = tmp_path / "tuned"
    done = meniscope("train", "--lab-video", str(lab), "--out", str(tuned), "--quick", "--init", str(out))
    assert done.returncode == 0, done.stderr
    assert load_manifest(tuned, scene).training.config["net"]["channels"] == [4, 8, 8]


def test_training_refuses_bad_input_in_one_line(trained: tuple[Path, Path, Path], tmp_path: Path) -> None:
    lab, _, _ = trained
    done = meniscope("train", "--lab-video", str(tmp_path / "none.cine"), "--out", str(tmp_path / "m"), "--quick")
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "none.cine" in done.stderr
    done = meniscope("train", "--lab-video", str(lab), "--holdout", str(lab), "--out", str(tmp_path / "m"), "--quick")
    assert done.returncode == 2 and "hold-out recording must differ" in done.stderr
    done = meniscope("train", "--lab-video", str(lab), "--out", str(tmp_path / "m40"), "--quick", "--input-px", "40")
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "--input-px" in done.stderr
    assert not (tmp_path / "m40").exists()
    for channels in ("8,x", "8,0", ""):
        done = meniscope(
            "train", "--lab-video", str(lab), "--out", str(tmp_path / "mc"), "--quick", "--channels", channels
        )
        assert done.returncode == 2 and done.stderr.count("\n") == 1 and "--channels" in done.stderr
    assert not (tmp_path / "mc").exists()
