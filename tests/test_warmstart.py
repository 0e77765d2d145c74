"""Warm starts (``meniscope train --init MODELS``): a model folder's ONNX graphs read back into torch modules that
compute what the graphs compute, refused in one line when the shapes differ, and fine-tuned for another scene."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service import DEFAULT_MODELS
from service.errors import MeniscopeError
from service.inverse.manifest import load_manifest
from service.scene import Scene
from tests.servicekit import meniscope

torch = pytest.importorskip("torch", reason="warm starts need the train extra (torch)")
ort = pytest.importorskip("onnxruntime")

from training.normalise import Normalise  # noqa: E402
from training.regressor import LatentRegressor  # noqa: E402
from training.vae import NetConfig  # noqa: E402
from training.warmstart import load_warm_start  # noqa: E402

#: Shipped graphs and the torch modules read back from them agree within this (mm): float32 rounding only.
PARITY_MM = 1e-5


@pytest.fixture(scope="module")
def shipped() -> tuple:
    """The shipped folder's modules and its network and direct graphs."""
    warm = load_warm_start(DEFAULT_MODELS, NetConfig(), Normalise(3), 96, 96)
    graphs = {name: ort.InferenceSession(str(DEFAULT_MODELS / f"{name}.onnx")) for name in ("network", "direct")}
    return warm, graphs


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    peak=st.sampled_from([1, 255, 4095, 65535]),
    frames=st.integers(1, 5),
)
def test_modules_read_back_compute_what_the_shipped_graphs_compute(
    shipped: tuple, seed: int, peak: int, frames: int
) -> None:
    """Any frames, from flat black to full-scale 16-bit noise: torch and onnxruntime agree on every output."""
    warm, graphs = shipped
    x = np.random.default_rng(seed).integers(0, peak + 1, (frames, 96, 96)).astype(np.uint16)
    modules = {
        "network": LatentRegressor(Normalise(3), warm.vae.encoder, warm.head).eval(),
        "direct": warm.direct.eval(),
    }
    for name, module in modules.items():
        with torch.no_grad():
            coefficients, centre = module(torch.from_numpy(x.astype(np.int32)))
        expected = graphs[name].run(None, {"frames": x})
        np.testing.assert_allclose(coefficients.numpy(), expected[0], atol=PARITY_MM)
        np.testing.assert_allclose(centre.numpy(), expected[1], atol=PARITY_MM)


def test_another_network_shape_is_refused_in_one_line() -> None:
    with pytest.raises(MeniscopeError, match="warm starts need the same shapes") as info:
        load_warm_start(DEFAULT_MODELS, NetConfig(input_px=48), Normalise(2), 96, 96)
    assert "\n" not in str(info.value)


def test_a_folder_without_a_manifest_or_with_a_changed_file_is_refused(tmp_path: Path) -> None:
    with pytest.raises(MeniscopeError, match="no manifest.json"):
        load_warm_start(tmp_path, NetConfig(), Normalise(3), 96, 96)
    for name in ("manifest.json", "network.onnx", "direct.onnx", "autoencoder.onnx"):
        (tmp_path / name).write_bytes((DEFAULT_MODELS / name).read_bytes())
    (tmp_path / "direct.onnx").write_bytes(b"changed")
    with pytest.raises(MeniscopeError, match="changed since manifest.json"):
        load_warm_start(tmp_path, NetConfig(), Normalise(3), 96, 96)


def test_fine_tuning_makes_models_for_another_scene_from_the_shipped_ones(tmp_path: Path, scene: Scene) -> None:
    """--init starts from the shipped weights and records where they came from; the folder is for the new scene."""
    mirror = scene.model_copy(update={"fluid": scene.fluid.model_copy(update={"roughness": 0.004})})
    scene_file = tmp_path / "mirror.json"
    scene_file.write_text(json.dumps(mirror.model_dump(mode="json")))
    lab = tmp_path / "lab.cine"
    assert meniscope("simulate", "--scene", scene_file, "--out", lab, "--windows", "2", "--seed", "3").returncode == 0
    done = meniscope(
        "train", "--scene", scene_file, "--lab-video", lab, "--out", tmp_path / "m", "--quick", "--init", DEFAULT_MODELS
    )
    assert done.returncode == 0, done.stderr
    manifest = load_manifest(tmp_path / "m", mirror)
    assert manifest.training.config["init"] == str(DEFAULT_MODELS)
    with pytest.raises(MeniscopeError, match="trained for scene"):
        load_manifest(tmp_path / "m", scene)
    done = meniscope(
        "train", "--lab-video", lab, "--out", tmp_path / "m48", "--quick", "--input-px", "48", "--init", DEFAULT_MODELS
    )
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "same shapes" in done.stderr
    assert not (tmp_path / "m48").exists()
