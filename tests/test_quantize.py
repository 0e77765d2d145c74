"""``meniscope quantize``: an int8 copy of a model folder that the service opens like any other, whose
coefficients stay near the float graphs' on renders no model saw, with how it was made and its parity in
its manifest; one-line errors for what users get wrong."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service import DEFAULT_MODELS
from service.errors import MeniscopeError
from service.inverse.manifest import load_manifest
from service.inverse.methods import open_method
from service.scene import Scene
from tests.servicekit import meniscope

pytest.importorskip("onnx", reason="quantising needs the train extra (onnx)")
from training.quantize import quantize_models, renders

#: The int8 graphs' promise on renders no model saw: each coefficient (d, p, a, b; mm, -, mm, mm) within
#: these of the float graph's; D(0, t) within this RMS (mm) of the float graph's (its own error against
#: the truth is ~8-18 um); and their error against the truth at most this share above the float graph's.
#: Measured on 200 renders: 8.4, 43, 4.4, 3.2 (1e-3) at most, 2.2 um RMS, under 1 % more error.
INT8_MAX_DIFF = np.array([0.02, 0.1, 0.01, 0.01])
INT8_RMS_DIFF_MM, INT8_EXTRA_ERROR = 0.004, 0.10


def test_the_manifest_says_it_is_int8_how_it_was_made_and_how_far_it_lies_from_float(int8: Path, scene: Scene):
    manifest, source = load_manifest(int8, scene), load_manifest(DEFAULT_MODELS, scene)
    q = manifest.quantisation
    assert q.mode == "static" and q.calibration == {"renders": 128, "seed": 3} and q.weights.startswith("int8")
    assert q.source["path"] == str(DEFAULT_MODELS) and source.quantisation is None
    assert manifest.input == source.input and manifest.training == source.training
    assert manifest.autoencoder is None  # figures only: not quantised, not copied
    for name, parity in q.parity.items():
        # the trunk's convolutions after the first, and their ReLUs
        assert [n.split("/")[-1] for n in q.nodes if n.startswith(f"{name}: ")] == ["Conv", "Conv", "Relu", "Relu"]
        assert parity.frames == 128 and set(parity.max_abs) == {"d", "p", "a", "b", "centre"}
        assert manifest.methods[name].parity_max_abs == max(parity.max_abs.values()) > 0
        assert parity.int8.rmse["centre"] <= (1 + INT8_EXTRA_ERROR) * parity.float32.rmse["centre"]


def test_the_service_opens_it_and_its_coefficients_stay_near_the_float_ones(int8: Path, scene: Scene):
    frames, truth = renders(scene, 200, seed=5, bit_depth=12)  # seeded apart from calibration and parity
    for name in ("network", "direct"):
        reference = open_method(name, scene, DEFAULT_MODELS)[0].infer(frames)
        got = open_method(name, scene, int8)[0].infer(frames)
        assert np.all(np.abs(got.coefficients - reference.coefficients).max(axis=0) < INT8_MAX_DIFF)
        assert np.sqrt(np.mean((got.centre - reference.centre) ** 2)) < INT8_RMS_DIFF_MM
        error = {
            k: np.sqrt(np.mean((out.centre - truth[:, 4]) ** 2)) for k, out in (("float", reference), ("int8", got))
        }
        assert error["int8"] <= (1 + INT8_EXTRA_ERROR) * error["float"], (name, error)


def test_dynamic_quantisation_is_a_choice_with_no_calibration(tmp_path: Path, scene: Scene):
    manifest = quantize_models(DEFAULT_MODELS, tmp_path / "dyn", scene, "dynamic", parity_frames=32)
    assert manifest.quantisation.mode == "dynamic" and manifest.quantisation.calibration == {}
    frames, _ = renders(scene, 8, seed=5, bit_depth=12)
    assert np.all(np.isfinite(open_method("network", scene, tmp_path / "dyn")[0].infer(frames).coefficients))


def test_what_cannot_be_quantised_is_refused_in_one_line(int8: Path, scene: Scene, tmp_path: Path):
    with pytest.raises(MeniscopeError, match="already int8"):
        quantize_models(int8, tmp_path / "again", scene)
    copy = tmp_path / "models"
    shutil.copytree(DEFAULT_MODELS, copy)
    with pytest.raises(MeniscopeError, match="must differ from --models"):
        quantize_models(copy, copy, scene)
    done = meniscope("quantize", "--models", tmp_path / "none", "--out", tmp_path / "q")
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "none" in done.stderr
    done = meniscope("quantize", "--models", DEFAULT_MODELS, "--out", tmp_path / "q", "--calibration", "1")
    assert done.returncode == 2 and "--calibration" in done.stderr


def test_quantising_needs_no_torch() -> None:
    """`meniscope quantize` works on ONNX graphs (onnxruntime.quantization): loading it imports no torch."""
    check = "import sys, training.quantize; assert 'torch' not in sys.modules, 'training.quantize imported torch'"
    done = subprocess.run(
        [sys.executable, "-c", check],
        cwd=Path(__file__).resolve().parents[1],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
