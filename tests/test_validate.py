"""``meniscope validate``: every inverse method scored on a simulated recording, figures drawn, the manifest kept
loadable; and the ``database`` verb that builds what the nearest-neighbour methods search."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from service.camera_effects import noise_preset
from service.cli import main
from service.errors import MeniscopeError
from service.inverse.manifest import load_manifest
from service.inverse.methods import open_method
from service.inverse.nearest import NearestDatabase, NearestMethod
from service.inverse.network import NetworkMethod
from service.recordings.roi import read_roi_frames
from service.render import Renderer
from service.scene import Scene
from service.simulate import simulate, truth_path
from service.validation.report import validate
from service.validation.truth import oscillation_truth, read_truth
from training.dataset import DatasetConfig, generate

MODELS = Path(__file__).resolve().parents[1] / "models" / "default"
METHODS = ("nearest", "nearest-approx", "regularised")


@pytest.fixture(scope="module")
def inputs(scene: Scene, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path]]:
    """A two-window recording no model saw and two small render databases of different sizes."""
    folder = tmp_path_factory.mktemp("validate")
    rec = folder / "rec.cine"
    simulate(
        scene,
        rec,
        windows=2,
        seed=41,
        effects=noise_preset("lab", 12),
        renderer=Renderer(scene, supersample=1, sun_samples=2),
    )
    databases = [folder / "small", folder / "large"]
    for db, samples in zip(databases, (256, 768)):
        generate(DatasetConfig(scene=scene, samples=samples, seed=1, chunk_size=256, supersample=1), db)
    return rec, databases


@pytest.fixture(scope="module")
def validated(
    scene: Scene, inputs: tuple[Path, list[Path]], tmp_path_factory: pytest.TempPathFactory
) -> tuple[dict, Path]:
    """The document ``validate`` returns and the folder it drew into."""
    rec, databases = inputs
    out = tmp_path_factory.mktemp("figures")
    return validate(scene, MODELS, databases, [rec], out), out


@pytest.fixture(scope="module")
def document(validated: tuple[dict, Path]) -> dict:
    return validated[0]


def test_every_method_is_scored_on_every_oscillating_frame(
    document: dict, inputs: tuple[Path, list[Path]], scene: Scene
) -> None:
    rec, _ = inputs
    result = document["recordings"]["rec.cine"]
    idx, _ = oscillation_truth(read_truth(rec), scene)
    assert result["frames_scored"] == len(idx) == 2 * (190 - 5)
    expected = {"network", "direct"} | {f"{m}[{db}]" for m in METHODS for db in ("small", "large")}
    assert set(result["methods"]) == expected
    for scores in result["methods"].values():
        assert scores["frames"] == len(idx) and set(scores["rmse"]) == {"d", "p", "a", "b", "centre"}
        assert all(np.isfinite(v) and v >= 0 for v in scores["rmse"].values()) and scores["seconds_per_frame"] > 0
    # the shipped networks follow the motion of a recording from our renderer
    assert result["methods"]["direct"]["centre_correlation"] > 0.8
    assert result["methods"]["network"]["centre_correlation"] > 0.4
    for db in ("small", "large"):
        search = result["search"][db]
        assert 0.5 <= search["recall_at_k"] <= 1.0 and search["exact_ms_per_frame"] > 0
        fits = result["window_fits"][f"regularised[{db}]"]
        assert fits["windows"] == 2 and np.isfinite(fits["frequency_rel_error_median"])


def test_the_nearest_scores_match_an_independent_computation(
    document: dict, inputs: tuple[Path, list[Path]], scene: Scene
) -> None:
    rec, databases = inputs
    idx, true = oscillation_truth(read_truth(rec), scene)
    frames, _ = read_roi_frames(rec, scene)
    centre = NearestMethod(NearestDatabase.load(databases[1])).infer(frames[idx]).centre
    rmse = np.sqrt(np.mean((centre - true[:, 4]) ** 2))
    got = document["recordings"]["rec.cine"]["methods"]["nearest[large]"]
    assert got["rmse"]["centre"] == pytest.approx(rmse, rel=1e-6)
    assert got["centre_correlation"] == pytest.approx(np.corrcoef(centre, true[:, 4])[0, 1], rel=1e-6)
    half = len(idx) // 2  # two windows of equal length: take each one's mean out
    inside = [np.concatenate([v[:half] - v[:half].mean(), v[half:] - v[half:].mean()]) for v in (centre, true[:, 4])]
    assert got["oscillation"]["rmse"] == pytest.approx(np.sqrt(np.mean((inside[0] - inside[1]) ** 2)), rel=1e-6)
    assert got["oscillation"]["correlation"] == pytest.approx(np.corrcoef(*inside)[0, 1], rel=1e-6)


def test_the_figures_are_written_and_named_in_the_document(validated: tuple[dict, Path], scene: Scene) -> None:
    document, out = validated
    assert json.loads((out / "figures.json").read_text()) == document
    figures = document["figures"]
    assert ("reconstructions" in figures) == (load_manifest(MODELS, scene).autoencoder is not None)
    assert {"centre rec.cine", "inferred renders"} <= set(figures)
    for name in figures.values():
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and (out / name).stat().st_size > 10_000


def test_recording_scores_in_the_manifest_keeps_the_model_loadable(
    scene: Scene, inputs: tuple[Path, list[Path]], tmp_path: Path
) -> None:
    rec, databases = inputs
    models = tmp_path / "models"
    shutil.copytree(MODELS, models)
    before = load_manifest(models, scene)
    validate(scene, models, databases[:1], [rec], tmp_path / "figures", record=True)
    after = load_manifest(models, scene)
    assert after.files == before.files
    assert set(after.validation["network"]) == set(before.validation["network"]) | {"rec.cine"}
    assert after.validation["direct"]["rec.cine"].frames == 370
    NetworkMethod(models, scene, "network")


def test_bad_input_is_one_line_naming_the_file(
    inputs: tuple[Path, list[Path]], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    rec, databases = inputs
    bare = tmp_path / "bare.cine"
    shutil.copy(rec, bare)  # a recording without its truth file
    other = tmp_path / "other.cine"
    shutil.copy(rec, other)  # a recording whose truth says it was made for another scene
    truth_path(other).write_text(json.dumps({**read_truth(rec), "scene_sha256": "0" * 64}))
    cases = [
        (["--recording", str(other)], "other.cine: simulated for scene 000000000000, not this one"),
        (["--recording", str(bare), "--database", str(databases[0])], f"{truth_path(bare)}: missing"),
        (
            ["--recording", str(rec), "--database", str(databases[0]), "--database", str(databases[0])],
            "--database: file and folder names must differ",
        ),
        (["--recording", str(rec), "--database", str(tmp_path)], "frames.npy: missing"),
    ]
    for argv, message in cases:
        assert main(["validate", "--models", str(MODELS), "--out", str(tmp_path / "out"), *argv]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1


def test_a_database_of_another_roi_size_is_refused_as_the_service_refuses_it(
    inputs: tuple[Path, list[Path]], scene: Scene, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    rec, _ = inputs
    other = tmp_path / "48px"
    other.mkdir()
    rng = np.random.default_rng(0)
    np.save(other / "frames.npy", rng.integers(0, 256, (16, 48, 48), dtype=np.uint8))  # renders of a 48 x 48 ROI
    np.save(other / "coeffs.npy", rng.normal(size=(16, 4)))
    np.save(other / "centre.npy", rng.normal(size=16))
    with pytest.raises(MeniscopeError) as refused:
        open_method("nearest", scene, MODELS, other)
    assert "renders of 48x48 px do not match the scene's ROI 96x96" in str(refused.value)
    argv = [
        "validate",
        "--models",
        str(MODELS),
        "--out",
        str(tmp_path / "out"),
        "--recording",
        str(rec),
        "--database",
        str(other),
    ]
    assert main(argv) == 2
    assert capsys.readouterr().err == f"meniscope validate: error: {refused.value}\n"


def test_the_database_verb_writes_a_searchable_database(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "db"
    assert main(["database", "--samples", "64", "--chunk-size", "32", "--workers", "1", "--out", str(out)]) == 0
    assert "indexed 64 renders" in capsys.readouterr().out
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["seed"] == 1  # apart from the training renders (seed 0)
    frames = np.load(out / "frames.npy")
    assert np.all(NearestDatabase.load(out).search(frames[:8], k=1).distance[:, 0] < 1e-3)
