"""The window model (issue 17): its features, its ONNX graph against torch, and its one place in the pipeline."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from service import DEFAULT_MODELS
from service.analysis.results import FitSettings
from service.analysis.segment import Window
from service.errors import MeniscopeError
from service.inverse import window_model as wm
from service.inverse.manifest import sha256_file
from service.pipeline.records import FRAME
from service.pipeline.windows import job_for, window_model_for
from training.window import WindowNet, export


def _records(m: int, rng: np.random.Generator) -> np.ndarray:
    """A window's records: an oscillating a and b, steady d and p, a brightness that follows them."""
    t = np.arange(m)
    records = np.zeros(m, FRAME)
    records["d"], records["p"] = 0.01, 0.05
    records["a"] = 0.004 * np.exp(-t / 80) * np.cos(2 * np.pi * t / 19)
    records["b"] = 0.001 * np.exp(-t / 40) * np.cos(2 * np.pi * t / 8)
    records["brightness"] = 900 * (1 + 3 * records["a"]) + rng.normal(0, 1, m)
    records["highlight"] = 0.5
    return records


@pytest.fixture(scope="module")
def graph(tmp_path_factory: pytest.TempPathFactory) -> tuple[WindowNet, Path]:
    """An untrained net with a non-zero output layer (a trained one's starts at zero) and its export."""
    torch.manual_seed(1)
    net = WindowNet()
    torch.nn.init.normal_(net.out.weight, std=0.3)
    path = tmp_path_factory.mktemp("window") / wm.FILE
    export(net.eval(), path)
    network = path.with_name(wm.NETWORK)
    network.write_bytes(b"a per-frame network")
    path.with_name(wm.RECORD).write_text(json.dumps({"network_sha256": sha256_file(network)}))
    return net, path


@pytest.mark.parametrize("frames", [20, 190, 400])
def test_the_onnx_graph_gives_torch_s_correction_at_any_window_length(graph, frames: int) -> None:
    net, path = graph
    rng = np.random.default_rng(frames)
    r = _records(frames, rng)
    coefficients = np.column_stack([r[k] for k in ("d", "p", "a", "b")])
    steady = 0.01 + 0.05 * 0.25 + r["a"] + r["b"]
    features = wm.window_features(coefficients, r["brightness"], steady, 6)
    with torch.no_grad():
        expected = net(torch.from_numpy(features[None]))[0].numpy()
    corrected = wm.WindowModel(path).correct(coefficients, r["brightness"], steady, 6)
    np.testing.assert_allclose((corrected - steady) / wm.SCALE_MM, expected, rtol=1e-4, atol=1e-5)


@settings(max_examples=40, deadline=None)
@given(
    gain=st.floats(1e-3, 1e3),
    missing=st.lists(st.integers(0, 99), max_size=30),
    skip=st.integers(0, 120),
)
def test_features_are_finite_blind_to_the_camera_gain_and_zero_where_frames_are_missing(
    gain: float, missing: list[int], skip: int
) -> None:
    r = _records(100, np.random.default_rng(0))
    coefficients = np.column_stack([r[k] for k in ("d", "p", "a", "b")])
    steady = coefficients[:, 0] + coefficients[:, 2]
    coefficients[missing] = np.nan
    plain = wm.window_features(coefficients, r["brightness"], steady, skip)
    scaled = wm.window_features(coefficients, gain * r["brightness"], steady, skip)
    assert np.isfinite(plain).all()
    np.testing.assert_allclose(plain, scaled, rtol=1e-4, atol=1e-5)
    assert not plain[8, missing].any() and not plain[:6, missing].any()
    assert plain[7].sum() == min(skip, 100)


def test_a_window_fitted_with_the_window_model_keeps_its_missing_frames_missing(graph) -> None:
    _, path = graph
    r = _records(190, np.random.default_rng(2))
    r["a"][50:60] = np.nan
    window = Window(0, 0, 190, True, True)
    plain = job_for(window, r, 0.25, 6)
    corrected = job_for(window, r, 0.25, 6, model=wm.WindowModel(path))
    np.testing.assert_array_equal(np.isnan(plain.series), np.isnan(corrected.series))
    assert np.nanmax(np.abs(corrected.series - plain.series)) > 0


def test_a_window_model_trained_on_another_per_frame_network_is_refused(graph, tmp_path: Path) -> None:
    _, path = graph
    for name in (wm.FILE, wm.RECORD):
        shutil.copy(path.with_name(name), tmp_path / name)
    (tmp_path / wm.NETWORK).write_bytes(b"a network trained again")
    with pytest.raises(MeniscopeError, match="trained on another network.onnx"):
        wm.WindowModel.of_folder(tmp_path)


def test_the_settings_choose_the_shipped_window_model_for_analyze_and_serve_alike() -> None:
    assert window_model_for(FitSettings(series_model="steady"), DEFAULT_MODELS, "network") is None
    assert window_model_for(FitSettings(series_model="window"), DEFAULT_MODELS, "nearest") is None
    if not (DEFAULT_MODELS / wm.FILE).is_file():
        pytest.skip(f"no {wm.FILE} in {DEFAULT_MODELS}")
    model = window_model_for(FitSettings(series_model="window"), DEFAULT_MODELS, "network")
    assert model is not None and model.path == DEFAULT_MODELS / wm.FILE
