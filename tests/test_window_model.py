"""The window model (issue 17): its features, its ONNX graph against torch, and its one place in the pipeline."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from service import DEFAULT_MODELS, DEFAULT_SCENE
from service.analysis.results import FitSettings, ModeEstimate, WindowResult
from service.analysis.segment import Window
from service.errors import MeniscopeError
from service.inverse import window_model as wm
from service.inverse.manifest import sha256_file
from service.pipeline.records import FRAME, LATENT_SIZE
from service.pipeline.windows import WindowJob, fit_job, job_for, window_model_for
from service.scene import Scene
from service.simulate import WindowRanges
from service.validation.score import QUANTITIES
from training import window as tw
from training.window import WindowNet, export
from training.window_intervals import calibrate, calibrate_folder


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
    corrected = wm.WindowModel(path).correct(coefficients, r["brightness"], steady, 6, r["latent"])
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


@pytest.fixture(scope="module")
def latent_graph(tmp_path_factory: pytest.TempPathFactory) -> tuple[WindowNet, Path]:
    """An untrained net taking the network's latent too, exported with the record that names its features."""
    torch.manual_seed(2)
    net = WindowNet(wm.FEATURES + LATENT_SIZE)
    torch.nn.init.normal_(net.out.weight, std=0.3)
    path = tmp_path_factory.mktemp("latent") / wm.FILE
    export(net.eval(), path)
    network = path.with_name(wm.NETWORK)
    network.write_bytes(b"a per-frame network with a latent")
    features = list(wm.FEATURE_NAMES + wm.LATENT_FEATURES)
    path.with_name(wm.RECORD).write_text(json.dumps({"network_sha256": sha256_file(network), "features": features}))
    return net, path


def test_a_window_model_taking_the_latent_gives_torch_s_correction_and_reads_it(latent_graph) -> None:
    net, path = latent_graph
    rng = np.random.default_rng(5)
    r = _records(190, rng)
    r["latent"] = rng.normal(0, 1, (190, LATENT_SIZE))
    coefficients = np.column_stack([r[k] for k in ("d", "p", "a", "b")])
    steady = 0.01 + 0.05 * 0.25 + r["a"] + r["b"]
    features = wm.window_features(coefficients, r["brightness"], steady, 6, r["latent"])
    with torch.no_grad():
        expected = net(torch.from_numpy(features[None]))[0].numpy()
    model = wm.WindowModel(path)
    corrected = model.correct(coefficients, r["brightness"], steady, 6, r["latent"])
    assert model.latent
    np.testing.assert_allclose((corrected - steady) / wm.SCALE_MM, expected, rtol=1e-4, atol=1e-5)
    other = model.correct(coefficients, r["brightness"], steady, 6, r["latent"][::-1])
    assert np.abs(other - corrected).max() > 0  # the latent is read, not ignored


@settings(max_examples=40, deadline=None)
@given(missing=st.lists(st.integers(0, 99), max_size=30), scale=st.floats(-1e3, 1e3), skip=st.integers(0, 120))
def test_the_latent_adds_its_channels_after_the_others_and_a_frame_without_one_is_missing(
    missing: list[int], scale: float, skip: int
) -> None:
    """The first :data:`wm.FEATURES` channels are those of a model without the latent, but for the frames whose
    latent is not there: those are missing in every channel."""
    r = _records(100, np.random.default_rng(1))
    latent = scale * np.random.default_rng(2).normal(0, 1, (100, LATENT_SIZE)).astype(np.float32)
    latent[missing] = np.nan
    coefficients = np.column_stack([r[k] for k in ("d", "p", "a", "b")])
    steady = coefficients[:, 0] + coefficients[:, 2]
    plain = wm.window_features(coefficients, r["brightness"], steady, skip)
    with_latent = wm.window_features(coefficients, r["brightness"], steady, skip, latent)
    kept = np.setdiff1d(np.arange(100), missing)
    assert with_latent.shape == (wm.FEATURES + LATENT_SIZE, 100) and np.isfinite(with_latent).all()
    np.testing.assert_array_equal(with_latent[wm.FEATURES :, kept], latent[kept].T)
    assert not with_latent[wm.PRESENT, missing].any() and not with_latent[wm.FEATURES :, missing].any()
    assert with_latent[wm.PRESENT, kept].all() and plain[wm.PRESENT].all()
    np.testing.assert_array_equal(with_latent[[6, 7]], plain[[6, 7]])  # time and transient do not depend on it


@pytest.mark.parametrize(
    ("features", "message"),
    [
        (list(wm.FEATURE_NAMES + wm.LATENT_FEATURES), "takes 9 features per frame, not the 19 window.json names"),
        (["d", "p"], "its features .* are not ones the window model is given"),
    ],
)
def test_a_window_model_whose_record_names_other_features_than_its_graph_takes_is_refused_in_one_line(
    graph, tmp_path: Path, features: list[str], message: str
) -> None:
    _, path = graph
    for name in (wm.FILE, wm.NETWORK):
        shutil.copy(path.with_name(name), tmp_path / name)
    record = json.loads(path.with_name(wm.RECORD).read_text()) | {"features": features}
    (tmp_path / wm.RECORD).write_text(json.dumps(record))
    with pytest.raises(MeniscopeError, match=message) as refused:
        wm.WindowModel.of_folder(tmp_path)
    assert "\n" not in str(refused.value) and str(tmp_path) in str(refused.value)


def test_the_settings_choose_the_shipped_window_model_for_analyze_and_serve_alike() -> None:
    assert window_model_for(FitSettings(series_model="steady"), DEFAULT_MODELS, "network") is None
    assert window_model_for(FitSettings(series_model="window"), DEFAULT_MODELS, "nearest") is None
    if not (DEFAULT_MODELS / wm.FILE).is_file():
        pytest.skip(f"no {wm.FILE} in {DEFAULT_MODELS}")
    model = window_model_for(FitSettings(series_model="window"), DEFAULT_MODELS, "network")
    assert model is not None and model.path == DEFAULT_MODELS / wm.FILE


def _result(amplitude: float, half: float, offset: float) -> WindowResult:
    """A one-mode window with the fit's own intervals of +-``half`` (relative) about its estimates."""
    return WindowResult(
        index=0,
        start_frame=0,
        end_frame=190,
        status="ok",
        modes=[
            ModeEstimate(
                frequency_hz=1500.0,
                decay_rate_per_s=300.0,
                amplitude_mm=amplitude,
                phase_rad=0.0,
                frequency_ci_hz=(1500.0 * (1 - half), 1500.0 * (1 + half)),
                decay_rate_ci_per_s=(300.0 * (1 - half), 300.0 * (1 + half)),
                amplitude_ci_mm=(amplitude * (1 - half), amplitude * (1 + half)),
            )
        ],
        offset_mm=offset,
        offset_ci_mm=(offset - half * 1e-3, offset + half * 1e-3),
        intervals="fit",
    )


@settings(max_examples=60, deadline=None)
@given(
    amplitude=st.floats(0.0, 0.05),
    half=st.floats(0.0, 2.0),
    offset=st.floats(-0.1, 0.1),
    factor=st.floats(0.0, 1e3),
    floor=st.floats(0.0, 1.0),
    log=st.booleans(),
)
def test_calibrated_intervals_are_finite_hold_the_estimate_and_keep_amplitudes_non_negative(
    amplitude: float, half: float, offset: float, factor: float, floor: float, log: bool
) -> None:
    intervals = wm.Intervals(
        dict.fromkeys(wm.QUANTITIES, factor),
        dict.fromkeys(wm.QUANTITIES, floor),
        {q: log and q != "offset" for q in wm.QUANTITIES},
        100,
        0.95,
    )
    out = intervals.apply(_result(amplitude, half, offset))
    mode = out.modes[0]
    assert out.intervals == "calibrated"
    for interval, estimate in (
        (mode.frequency_ci_hz, mode.frequency_hz),
        (mode.decay_rate_ci_per_s, mode.decay_rate_per_s),
        (mode.amplitude_ci_mm, mode.amplitude_mm),
        (out.offset_ci_mm, out.offset_mm),
    ):
        if interval is None:
            continue
        lo, hi = interval
        assert np.isfinite([lo, hi]).all() and lo <= estimate <= hi
    assert mode.amplitude_ci_mm is not None or (log and amplitude == 0)  # no ratio to a zero estimate
    if mode.amplitude_ci_mm is not None:
        assert mode.amplitude_ci_mm[0] >= 0 and mode.decay_rate_ci_per_s[0] >= 0
    json.loads(out.model_dump_json())  # plain JSON


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**16), spread=st.floats(0.01, 1.0), bias=st.floats(0.0, 0.5))
def test_conformal_factors_hold_the_truth_in_95_percent_of_the_calibration_windows(
    seed: int, spread: float, bias: float
) -> None:
    """Whatever the fit's errors (its own half-widths too narrow, a bias it cannot see), the calibrated intervals
    hold the truth in at least 95 % of the windows they were calibrated on, and in about as many new ones."""
    rng = np.random.default_rng(seed)

    def pairs(n: int) -> dict[str, np.ndarray]:
        true = rng.uniform(0.5, 2.0, n)
        est = true * (1 + bias + spread * rng.standard_normal(n))
        half = np.abs(est) * spread * rng.uniform(0.01, 0.3, n)
        return {
            f"{key}_{part}": value
            for key in QUANTITIES
            for part, value in (("est", est), ("true", true), ("lo", est - half), ("hi", est + half))
        }

    def coverage(p: dict[str, np.ndarray], intervals: wm.Intervals) -> float:
        est, true, lo, hi = (p[f"amplitude_{part}"] for part in ("est", "true", "lo", "hi"))
        low, high = intervals.bounds("amplitude", est, np.maximum(hi - est, est - lo))
        return float(np.mean((low <= true) & (true <= high)))

    calibration = pairs(400)
    intervals = calibrate(calibration, 0.95)
    assert intervals.windows == 400
    assert coverage(calibration, intervals) >= 0.95
    assert 0.90 <= coverage(pairs(4000), intervals) <= 0.99


def _linear_intervals(factor: float, floor: float) -> wm.Intervals:
    """A calibration with the same linear factor and floor for every quantity (240 windows, 95 %)."""
    return wm.Intervals(
        dict.fromkeys(wm.QUANTITIES, factor),
        dict.fromkeys(wm.QUANTITIES, floor),
        dict.fromkeys(wm.QUANTITIES, False),
        240,
        0.95,
    )


def test_the_calibration_travels_with_the_job_and_calibrates_the_fit(graph, tmp_path: Path) -> None:
    _, path = graph
    for name in (wm.FILE, wm.NETWORK):
        shutil.copy(path.with_name(name), tmp_path / name)
    record = json.loads(path.with_name(wm.RECORD).read_text())
    factors = _linear_intervals(3.0, 0.1)
    (tmp_path / wm.RECORD).write_text(json.dumps(record | {"intervals": factors.as_record()}))
    model = wm.WindowModel.of_folder(tmp_path)
    assert model.intervals == factors
    r = _records(190, np.random.default_rng(3))
    job = job_for(Window(0, 0, 190, True, True), r, 0.25, 6, model=model)
    assert job.intervals == factors
    assert wm.WindowModel(path).intervals is None  # a model without a calibration keeps the fit's intervals


def _wandering(steady: np.ndarray, height_mm: float, rise: float) -> np.ndarray:
    """``steady`` with a slow bump of ``height_mm`` peaking ``rise`` frames in: a correction that wanders."""
    t = np.arange(steady.size)
    return steady + height_mm * (t / rise) * np.exp(1 - t / rise)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**16), height=st.floats(0.002, 0.02), rise=st.floats(10.0, 60.0))
def test_a_settled_window_is_settled_whatever_the_window_models_correction_wanders(
    seed: int, height: float, rise: float
) -> None:
    """The window model de-shrinks oscillations; a slow swing or trend it adds to a steady series that has none
    above the noise does not make the meniscus move (a Blender recording's settled window came out unresolved)."""
    steady = 0.001 + np.random.default_rng(seed).normal(0, 0.0002, 190)
    job = WindowJob(Window(0, 0, 190, True, True), _wandering(steady, height, rise), None, 0.5, steady=steady)
    result = fit_job(job, 19_000.0, FitSettings())
    assert result.status == "settled" and not result.modes and result.settled
    assert 0 < result.residual_amplitude_mm < 0.001


def test_a_window_settled_from_its_steady_series_has_its_offsets_interval_calibrated_too() -> None:
    """The calibration is made on every window the default path reports, those settled from the steady series among
    them (``training.window_intervals``): their offset's interval is calibrated like any other's, not the fit's own
    (a few nm wide: it held the truth of none of them)."""
    steady = 0.001 + np.random.default_rng(1).normal(0, 0.0002, 190)
    calibration = _linear_intervals(3.0, 0.002)
    series = _wandering(steady, 0.01, 30.0)
    job = WindowJob(Window(0, 0, 190, True, True), series, None, 0.5, intervals=calibration, steady=steady)
    result = fit_job(job, 19_000.0, FitSettings())
    assert result.status == "settled" and result.intervals == "calibrated"
    low, high = result.offset_ci_mm
    assert low < result.offset_mm < high and high - low >= 2 * 3.0 * 0.002


def test_a_window_whose_steady_series_oscillates_keeps_the_window_models_fit() -> None:
    t = np.arange(190)
    steady = 0.001 + np.random.default_rng(0).normal(0, 0.0002, 190)
    steady += 0.002 * np.exp(-t / 80) * np.cos(2 * np.pi * t / 19)
    job = WindowJob(Window(0, 0, 190, True, True), _wandering(steady, 0.003, 30.0), None, 0.5, steady=steady)
    result = fit_job(job, 19_000.0, FitSettings())
    assert result.status != "settled" and any(abs(m.frequency_hz - 1000) < 20 for m in result.modes)


#: What :func:`training.window.render_training` was asked for: (windows, first seed, ranges, name, bit depth).
Asked = list[tuple[int, int, WindowRanges, str, int]]


def asked_of(render_some: Callable[[], list[Path]]) -> tuple[list[Path], Asked]:
    """The paths ``render_some`` returns with :func:`training.window.render_training` replaced by a recorder that
    renders nothing, and what it was asked for."""
    asked: Asked = []

    def render(
        folder: Path,
        scene: object,
        n: int,
        s: int,
        ranges: WindowRanges = tw.TRAINING_RANGES,
        name: str = "window",
        bit_depth: int = 12,
        vary: object = None,
    ) -> list[Path]:
        asked.append((n, s, ranges, name, bit_depth))
        return [folder / f"{name}-{noise}-{s + k}.cine" for k, noise in enumerate(tw.TRAINING_NOISE)]

    original, tw.render_training = tw.render_training, render
    try:
        return render_some(), asked
    finally:
        tw.render_training = original


@settings(max_examples=30, deadline=None)
@given(windows=st.integers(1, 5000), seed=st.integers(0, 10**6))
def test_training_windows_are_half_nominal_half_widened_at_seeds_of_their_own(windows: int, seed: int) -> None:
    """``train``'s training windows (:func:`training.window.render_mix`): per noise preset, half at the simulator's
    nominal motion (like the held-out recordings and the calibration) and the rest at the widened ranges, one in
    ``EIGHT_BIT_SHARE`` of each half through the 8-bit camera, each part at seeds that no other part nor the
    calibration (``seed + CALIBRATION_SEEDS`` on) uses."""
    paths, asked = asked_of(lambda: tw.render_mix(Path("data"), None, windows, seed))  # type: ignore[arg-type]
    assert sum(n for n, *_ in asked) == windows and all(n > 0 for n, *_ in asked)
    assert {r for _, _, r, _, _ in asked} <= {tw.TRAINING_RANGES, WindowRanges()}
    assert sum(n for n, _, r, _, _ in asked if r == WindowRanges()) == windows // 2
    for ranges, half in ((WindowRanges(), windows // 2), (tw.TRAINING_RANGES, windows - windows // 2)):
        eight = sum(n for n, _, r, _, bits in asked if r == ranges and bits == 8)
        assert eight == half // tw.EIGHT_BIT_SHARE
    assert {bits for *_, bits in asked} <= {8, 12}
    used = [s + k for _, s, *_ in asked for k in range(len(tw.TRAINING_NOISE))]
    calibrations = len(tw.TRAINING_NOISE) * len(tw.CALIBRATION_BIT_DEPTHS)
    calibration = {seed + tw.CALIBRATION_SEEDS + k for k in range(calibrations)}
    assert len(set(used)) == len(used) and not calibration & set(used)
    assert len(set(paths)) == len(paths) == len(tw.TRAINING_NOISE) * len(asked)


@settings(max_examples=30, deadline=None)
@given(windows=st.integers(1, 5000), seed=st.integers(0, 10**6))
def test_calibration_windows_cover_every_preset_through_the_12_and_the_8_bit_camera(windows: int, seed: int) -> None:
    """``train``'s calibration windows (:func:`training.window.render_calibration`): ``windows`` per noise preset
    and camera, all at the simulator's nominal motion, each recording at a seed of its own from
    ``seed + CALIBRATION_SEEDS`` on (none of which a training window uses: the test above)."""
    paths, asked = asked_of(lambda: tw.render_calibration(Path("data"), None, windows, seed))  # type: ignore[arg-type]
    assert sorted(bits for *_, bits in asked) == sorted(tw.CALIBRATION_BIT_DEPTHS) == [8, 12]
    assert all(n == windows and r == WindowRanges() for n, _, r, _, _ in asked)
    used = sorted(s + k for _, s, *_ in asked for k in range(len(tw.TRAINING_NOISE)))
    first = seed + tw.CALIBRATION_SEEDS
    assert used == list(range(first, first + len(tw.TRAINING_NOISE) * len(tw.CALIBRATION_BIT_DEPTHS)))
    assert len(set(paths)) == len(paths) == len(used)


def test_calibrating_a_model_folder_that_fails_leaves_the_folder_as_it_was(demo_cine: Path, tmp_path: Path) -> None:
    """The intervals are calibrated on a copy of the folder without them: the demo's 4 windows are too few, and the
    shipped folder copied here keeps every byte (it used to lose its intervals and no longer match its manifest)."""
    models = tmp_path / "models"
    shutil.copytree(DEFAULT_MODELS, models)
    with pytest.raises(ValueError, match="too few to calibrate"):
        calibrate_folder(models, [demo_cine], Scene.load(DEFAULT_SCENE))
    for path in sorted(DEFAULT_MODELS.iterdir()):
        assert (models / path.name).read_bytes() == path.read_bytes(), path.name


@pytest.mark.parametrize("latent", [False, True])
def test_a_built_window_model_names_the_features_it_takes_and_loads_with_them(
    demo_cine: Path, tmp_path: Path, latent: bool
) -> None:
    """``training.window.build`` with or without the network's latent: the record names the channels the graph
    takes, and the runtime reads the latent exactly when the model was given it."""
    models = tmp_path / "models"
    shutil.copytree(DEFAULT_MODELS, models)
    record = tw.build(models, Scene.load(DEFAULT_SCENE), tmp_path, 0, 1, 0, 0, (demo_cine,), latent=latent)
    names = wm.FEATURE_NAMES + (wm.LATENT_FEATURES if latent else ())
    assert record["features"] == list(names)
    model = wm.WindowModel.of_folder(models)
    assert model.latent == latent
