"""Scenes randomised around a scene (training/window_scenes.py): valid at the extremes, reproducible by seed, and
rendered one world per recording with the world kept beside it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service import DEFAULT_SCENE
from service.camera_effects import CameraEffects, noise_preset
from service.inverse import window_model as wm
from service.scene import Scene
from service.simulate import WindowRanges
from service.validation.score import QUANTITIES
from training import window as tw
from training import window_intervals as wi
from training import window_scenes as ws

SCENE = Scene.load(DEFAULT_SCENE)


def _scene(roughness: float, reflectance: float, elevation: float, angle: float, exposure: float) -> Scene:
    """The default scene with its fluid, light and exposure at the given values."""
    return SCENE.model_copy(
        update={
            "fluid": {"roughness": roughness, "reflectance": reflectance},
            "light": SCENE.light.model_copy(update={"elevation_deg": elevation, "angle_deg": angle}),
            "camera": SCENE.camera.model_copy(update={"exposure": exposure}),
        }
    )


@settings(max_examples=80, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    roughness=st.sampled_from([1e-4, 0.003, 0.06, 0.9, 1.0]),
    reflectance=st.sampled_from([0.0, 0.05, 0.9, 1.0]),
    elevation=st.sampled_from([-90.0, -89.0, -40.0, 89.5, 90.0]),
    angle=st.sampled_from([0.0, 0.5, 4.0, 178.0, 179.0]),
    exposure=st.sampled_from([1e-3, 1.0, 50.0]),
    wide=st.booleans(),
)
def test_a_randomised_scene_is_valid_within_its_spread_and_keeps_the_geometry_and_pose(
    seed: int, roughness: float, reflectance: float, elevation: float, angle: float, exposure: float, wide: bool
) -> None:
    """At the scene file's limits (and with a spread far wider than the default) the drawn scene still validates,
    each quantity stays within its spread of the original (but where clipped to its valid range), and the nozzle,
    the camera's pose and the light's strength are the original's."""
    spread = ws.Spread(4.0, 0.8, 30.0, 4.0, 4.0, 5.0, 0.5, 10.0) if wide else ws.SPREAD
    scene = _scene(roughness, reflectance, elevation, angle, exposure)
    out = Scene.model_validate(ws.randomised(scene, np.random.default_rng(seed), spread).model_dump())
    ratio = out.fluid.roughness / scene.fluid.roughness
    assert 0 < out.fluid.roughness <= 1
    assert 1 / spread.roughness_factor - 1e-9 <= ratio <= spread.roughness_factor + 1e-9 or out.fluid.roughness in (
        1e-4,
        1.0,
    )
    assert abs(out.fluid.reflectance - reflectance) <= spread.reflectance + 1e-12
    assert abs(out.light.azimuth_deg - scene.light.azimuth_deg) <= spread.light_deg
    assert abs(out.light.elevation_deg - elevation) <= spread.light_deg and -90 <= out.light.elevation_deg <= 90
    assert 0 <= out.light.angle_deg <= 179
    assert out.light.angle_deg <= angle * spread.angle_factor + 1e-9
    assert 1 / spread.exposure_factor - 1e-9 <= out.camera.exposure / exposure <= spread.exposure_factor + 1e-9
    assert out.nozzle == scene.nozzle and out.light.strength == scene.light.strength
    assert out.camera.model_copy(update={"exposure": exposure}) == scene.camera
    assert all(math.isfinite(v) for v in (out.fluid.roughness, out.light.azimuth_deg, out.camera.exposure))


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    blur=st.sampled_from([0.0, 0.1, 9.9, 10.0]),
    offset=st.sampled_from([-1.0, -0.005, 0.0, 0.02, 1.0]),
    full_well=st.sampled_from([0.0, 1.0, 4000.0, 1e8]),
)
def test_a_randomised_camera_is_valid_at_its_limits(seed: int, blur: float, offset: float, full_well: float) -> None:
    """Blur, black level and full well drawn around a camera at the limits of each stay valid settings; a camera
    without shot noise (full well 0) stays without; the bit depth and read noise are the preset's."""
    effects = CameraEffects(blur_sigma_px=blur, offset=offset, full_well_e=full_well, read_noise_dn=1.5, bit_depth=12)
    out = CameraEffects.model_validate(ws.randomised_effects(effects, np.random.default_rng(seed)).model_dump())
    assert abs(out.blur_sigma_px - blur) <= ws.SPREAD.blur_px + 1e-12 and 0 <= out.blur_sigma_px <= 10
    assert abs(out.offset - offset) <= ws.SPREAD.black_level + 1e-12 and -1 <= out.offset <= 1
    assert (out.full_well_e == 0) == (full_well == 0)
    assert (out.bit_depth, out.read_noise_dn) == (12, 1.5)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_a_world_is_reproducible_by_its_seed_and_another_seed_draws_another(seed: int) -> None:
    """The same seed draws the same scene and camera; the next seed another."""
    effects = noise_preset("lab", 12)
    first = ws.vary(SCENE, effects, np.random.default_rng(seed))
    assert first == ws.vary(SCENE, effects, np.random.default_rng(seed))
    assert first != ws.vary(SCENE, effects, np.random.default_rng(seed + 1))


@pytest.mark.parametrize("varied", [False, True])
def test_each_varied_recording_is_rendered_from_its_own_world_written_beside_it(
    varied: bool, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With ``vary``, :func:`training.window.render_training` renders each preset's recording from a world of its
    own, drawn from the recording's seed, and writes it beside the recording (read back, the same scene and camera);
    without, one renderer of the scene itself serves every preset and nothing more is written."""
    import service.render
    import service.simulate

    renderers: list[Scene] = []
    rendered: list[tuple[Scene, CameraEffects, int]] = []

    def simulate(scene: Scene, out: Path, *, effects: CameraEffects, seed: int, **_: object) -> None:
        rendered.append((scene, effects, seed))
        service.simulate.truth_path(out).write_text("{}")

    monkeypatch.setattr(service.render, "Renderer", lambda scene: renderers.append(scene) or scene)
    monkeypatch.setattr(service.simulate, "simulate", simulate)
    paths = tw.render_training(tmp_path, SCENE, 3, 500, name="w", vary=ws.vary if varied else None)
    assert [seed for *_, seed in rendered] == [500, 501, 502]
    if not varied:
        assert renderers == [SCENE] and all(s == SCENE for s, *_ in rendered)
        assert not list(tmp_path.glob("*.world.json"))
        return
    assert renderers == [s for s, *_ in rendered] and len(set(renderers)) == 3 and SCENE not in renderers
    for path, (scene, effects, seed), noise in zip(paths, rendered, tw.TRAINING_NOISE):
        world = json.loads(path.with_name(path.name + ".world.json").read_text())
        assert Scene.model_validate(world["scene"]) == scene
        assert CameraEffects.model_validate(world["effects"]) == effects
        drawn = ws.vary(SCENE, noise_preset(noise, 12), np.random.default_rng([tw.VARY_KEY, seed]))
        assert drawn == (scene, effects)


@settings(max_examples=30, deadline=None)
@given(windows=st.integers(1, 3000), chunk=st.integers(1, 200), seed=st.integers(0, 10**6))
def test_randomised_windows_come_in_chunks_of_the_training_mix_at_seeds_of_their_own(
    windows: int, chunk: int, seed: int
) -> None:
    """:func:`training.window_scenes.render_randomised` asks :func:`training.window.render_mix` for ``windows`` per
    preset in all, in chunks of at most ``chunk``, each varied and at seeds no other chunk's recordings use."""
    asked: list[tuple[int, int, object]] = []

    def render_mix(data: Path, scene: Scene, n: int, s: int, vary: object = None) -> list[Path]:
        asked.append((n, s, vary))
        return [data / f"{s}.cine"]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ws, "render_mix", render_mix)
        paths = ws.render_randomised(Path("data"), SCENE, windows, seed, chunk)
    assert sum(n for n, *_ in asked) == windows and all(0 < n <= chunk for n, *_ in asked)
    assert all(v is ws.vary for *_, v in asked) and len(paths) == len(asked)
    # render_mix's recordings use seeds s + {0, EIGHT_BIT_SEEDS, NOMINAL_SEEDS, both} + preset
    offsets = {0, tw.EIGHT_BIT_SEEDS, tw.NOMINAL_SEEDS, tw.NOMINAL_SEEDS + tw.EIGHT_BIT_SEEDS}
    used = [s + o + k for _, s, _ in asked for o in offsets for k in range(len(tw.TRAINING_NOISE))]
    assert len(used) == len(set(used))


class _Asked(Exception):
    """Stops :func:`training.window.build` once its training recordings are known."""


@settings(max_examples=30, deadline=None)
@given(windows=st.integers(1, 3000), share=st.floats(0, 1), seed=st.integers(0, 10**6))
def test_build_draws_its_randomised_share_at_seeds_no_default_scene_window_uses(
    windows: int, share: float, seed: int
) -> None:
    """``build(..., randomised=N)`` trains on ``windows - N`` windows per preset of the scene itself and ``N`` of
    randomised scenes (in a folder of their own, at seeds from ``seed + RANDOMISED_SEEDS``: beyond the scene's
    training and calibration windows'), all replayed through the scene's own network."""
    randomised = int(share * windows)
    asked: dict[str, tuple[Path, int, int]] = {}

    def mix(data: Path, scene: Scene, n: int, s: int) -> list[Path]:
        asked["scene"] = (data, n, s)
        return [data / "a.cine"]

    def rand(data: Path, scene: Scene, n: int, s: int, chunk: int, world: object) -> list[Path]:
        assert world is ws.vary  # no calibration's ranges: randomised around the scene itself
        asked["randomised"] = (data, n, s)
        return [data / "b.cine"]

    def replayed(path: Path, scene: Scene, models: Path) -> tw.Examples:
        assert scene is SCENE
        raise _Asked

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(tw, "render_mix", mix)
        patch.setattr(ws, "render_randomised", rand)
        patch.setattr(tw, "cached_examples", replayed)
        with pytest.raises(_Asked):
            tw.build(Path("models"), SCENE, Path("data"), windows, 1, seed, 0, randomised=randomised)
    assert asked.get("scene") == ((Path("data"), windows - randomised, seed) if windows > randomised else None)
    if not randomised:
        assert "randomised" not in asked
        return
    folder, n, first = asked["randomised"]
    assert folder != Path("data") and n == randomised
    # the scene's own windows use seeds up to seed + NOMINAL + EIGHT_BIT + presets, calibration seed + CALIBRATION..
    assert first > seed + max(tw.NOMINAL_SEEDS + tw.EIGHT_BIT_SEEDS, tw.CALIBRATION_SEEDS + 6) + len(tw.TRAINING_NOISE)


@pytest.mark.parametrize("randomised", [-1, 11])
def test_build_refuses_a_randomised_share_outside_its_windows(randomised: int) -> None:
    """More randomised windows than windows, or fewer than none, is an error before anything renders."""
    with pytest.raises(ValueError, match="randomised windows"):
        tw.build(Path("models"), SCENE, Path("data"), 10, 1, 0, 0, randomised=randomised)


@settings(max_examples=40, deadline=None)
@given(windows=st.integers(0, 400), randomised=st.integers(0, 2000), seed=st.integers(0, 10**6))
def test_randomised_calibration_windows_come_from_worlds_of_their_own_at_seeds_no_other_window_uses(
    windows: int, randomised: int, seed: int
) -> None:
    """:func:`training.window.render_calibration` with ``randomised``: besides the scene's ``windows`` per preset
    and camera, ``randomised`` more per preset and camera at the nominal motion from at most
    :data:`training.window.CALIBRATION_WORLDS` varied recordings, at seeds that neither the scene's calibration nor
    any training window (:func:`training.window.render_mix`, :func:`training.window_scenes.render_randomised`) uses."""
    asked: list[tuple[int, int, object, str, int, object]] = []

    def render(
        folder: Path, scene: Scene, n: int, s: int, ranges: object, name: str, bits: int, vary: object = None
    ) -> list[Path]:
        asked.append((n, s, ranges, name, bits, vary))
        return [folder / f"{name}-{noise}-{s + k}.cine" for k, noise in enumerate(tw.TRAINING_NOISE)]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(tw, "render_training", render)
        paths = tw.render_calibration(Path("data"), SCENE, windows, seed, randomised)
    assert all(n > 0 and r == WindowRanges() for n, _, r, *_ in asked)
    for bits in tw.CALIBRATION_BIT_DEPTHS:
        scene_own = [n for n, _, _, _, b, v in asked if b == bits and v is None]
        varied = [n for n, _, _, _, b, v in asked if b == bits and v is ws.vary]
        assert sum(scene_own) == windows and len(scene_own) == (windows > 0)
        assert sum(varied) == randomised and len(varied) <= tw.CALIBRATION_WORLDS
        assert not varied or max(varied) - min(varied) <= 1  # the worlds share the windows evenly
    used = [s + k for _, s, *_ in asked for k in range(len(tw.TRAINING_NOISE))]
    assert len(used) == len(set(used)) == len(paths) == len(set(paths))
    # render_mix's recordings lie at seed + {0, EIGHT_BIT, NOMINAL, NOMINAL + EIGHT_BIT} + preset; the randomised
    # training windows from seed + RANDOMISED_SEEDS on
    mix = {seed + o + k for o in (0, tw.EIGHT_BIT_SEEDS) for k in range(len(tw.TRAINING_NOISE))}
    assert not mix & set(used)
    assert all(seed + tw.CALIBRATION_SEEDS <= s < seed + tw.NOMINAL_SEEDS for s in used)


@pytest.mark.parametrize("calibration", [(-1, None), (80, -1), (0, -5)])
def test_build_refuses_negative_calibration_windows(calibration: tuple[int, int | None]) -> None:
    """Fewer than no calibration windows, of the scene's or randomised, is an error before anything renders."""
    with pytest.raises(ValueError, match="calibration windows"):
        tw.build(Path("models"), SCENE, Path("data"), 10, 1, 0, calibration[0], calibration_randomised=calibration[1])


def test_intervals_cli_pools_randomised_windows_with_the_named_ones(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``python -m training.window_intervals --randomised N`` renders N windows per preset and camera from
    randomised worlds into ``--data`` (none of the scene's own) and calibrates on them and the named recordings
    together; without recordings or with ``--score`` it is refused in one line."""
    asked: dict[str, object] = {}

    def render(data: Path, scene: Scene, windows: int, seed: int, randomised: int) -> list[Path]:
        asked["render"] = (data, windows, seed, randomised)
        return [data / "r.cine"]

    def calibrate_folder(models: Path, recordings: list[Path], scene: Scene) -> wm.Intervals:
        asked["calibrate"] = recordings
        one = dict.fromkeys(wm.QUANTITIES, 1.0)
        return wm.Intervals(one, dict.fromkeys(wm.QUANTITIES, 0.0), dict.fromkeys(wm.QUANTITIES, False), 2, 0.95)

    monkeypatch.setattr(tw, "render_calibration", render)
    monkeypatch.setattr(wi, "calibrate_folder", calibrate_folder)
    wi.main(["--models", str(tmp_path), "--randomised", "3", "--data", str(tmp_path / "d"), "--seed", "7", "a.cine"])
    assert asked == {"render": (tmp_path / "d", 0, 7, 3), "calibrate": [Path("a.cine"), tmp_path / "d" / "r.cine"]}
    assert json.loads(capsys.readouterr().out)["windows"] == 2
    for argv in (["--randomised", "0"], ["--score", "--randomised", "2", "a.cine"], ["--randomised", "-1", "a.cine"]):
        with pytest.raises(SystemExit):
            wi.main(argv)
        assert "--randomised" in capsys.readouterr().err


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**16), shift=st.floats(0.3, 2.0), share=st.floats(0.3, 0.7))
def test_windows_of_randomised_worlds_pooled_in_widen_the_intervals_to_hold_them(
    seed: int, shift: float, share: float
) -> None:
    """Windows whose world is not the scene's err further than the fit can see: intervals calibrated on the scene's
    windows alone hold fewer of them than 95 %, and calibrated on both pooled they hold >= 95 % of the pool."""
    rng = np.random.default_rng(seed)

    def pairs(n: int, extra: float) -> dict[str, np.ndarray]:
        true = rng.uniform(-0.01, 0.01, n)  # an offset (mm)
        half = rng.uniform(2e-4, 5e-4, n)
        est = true + half * (rng.standard_normal(n) + extra * rng.standard_normal(n) * 3)
        return {
            f"{key}_{part}": value
            for key in QUANTITIES
            for part, value in (("est", est), ("true", true), ("lo", est - half), ("hi", est + half))
        }

    def coverage(p: dict[str, np.ndarray], intervals: wm.Intervals) -> float:
        est, true, lo, hi = (p[f"offset_mm_{part}"] for part in ("est", "true", "lo", "hi"))
        low, high = intervals.bounds("offset", est, np.maximum(hi - est, est - lo))
        return float(np.mean((low <= true) & (true <= high)))

    scene_own, worlds = pairs(400, 0.0), pairs(int(400 * share / (1 - share)), shift)
    pooled = {key: np.concatenate([scene_own[key], worlds[key]]) for key in scene_own}
    assert coverage(worlds, wi.calibrate(scene_own, 0.95)) < 0.95
    assert coverage(pooled, wi.calibrate(pooled, 0.95)) >= 0.95


@settings(max_examples=20, deadline=None)
@given(given_recordings=st.integers(1, 5), randomised=st.integers(1, 3000), seed=st.integers(0, 10**6))
def test_randomised_windows_go_on_top_of_named_recordings_when_render_equals_randomised(
    given_recordings: int, randomised: int, seed: int
) -> None:
    """``python -m training.window RECS... --render N --randomised N`` trains on every named recording, in its
    order, plus ``N`` randomised windows per preset, and renders none of the scene's own: the recipe of
    docs/window_model.md's "All the shipped windows plus randomised ones on top"."""
    named = tuple(Path(f"default-{k}.cine") for k in range(given_recordings))
    replayed: list[Path] = []

    def rand(data: Path, scene: Scene, n: int, s: int, chunk: int, world: object) -> list[Path]:
        assert n == randomised and s == seed + tw.RANDOMISED_SEEDS and world is ws.vary
        return [data / "r.cine"]

    def replay(path: Path, scene: Scene, models: Path) -> Path:
        replayed.append(path)
        return path

    def stop(parts: list[object]) -> tw.Examples:
        raise _Asked

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(tw, "render_training", lambda *a, **k: pytest.fail("rendered a window of the scene itself"))
        patch.setattr(ws, "render_randomised", rand)
        patch.setattr(tw, "cached_examples", replay)
        patch.setattr(tw, "concat", stop)
        with pytest.raises(_Asked):
            tw.build(Path("models"), SCENE, Path("data"), randomised, 1, seed, 0, named, randomised=randomised)
    assert replayed == [*named, Path("data") / "randomised" / "r.cine"]


#: A calibration's open ranges (the rough fluid B's report: docs/calibration.md).
OPEN = {"fluid.roughness": (0.097, 0.254), "light.angle_deg": (4.0, 10.15), "camera.elevation_deg": (-36.6, -33.6)}


@settings(max_examples=20, deadline=None)
@given(windows=st.integers(1, 3000), share=st.floats(0, 1), seed=st.integers(0, 10**6))
def test_build_over_open_ranges_renders_every_training_window_from_a_world_drawn_over_them(
    windows: int, share: float, seed: int
) -> None:
    """With a calibration's ``ranges``, the scene's own training windows come in chunks of
    :data:`training.window.RANGE_CHUNK`, a world drawn over the ranges per recording, at the scene's own seeds (in a
    folder of their own); the randomised ones are randomised around such draws; none is of the scene itself."""
    randomised = int(share * windows)
    asked: dict[str, tuple] = {}

    def rand(data: Path, scene: Scene, n: int, s: int, chunk: int, world: object) -> list[Path]:
        asked[data.name] = (n, s, chunk, world)
        return [data / "r.cine"]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(tw, "render_mix", lambda *a, **k: pytest.fail("rendered a window of the scene itself"))
        patch.setattr(ws, "render_randomised", rand)
        patch.setattr(tw, "cached_examples", lambda *a: (_ for _ in ()).throw(_Asked()))
        with pytest.raises(_Asked):
            tw.build(Path("models"), SCENE, Path("data"), windows, 1, seed, 0, randomised=randomised, ranges=OPEN)
    if windows > randomised:
        n, s, chunk, world = asked.pop("over-ranges")
        assert (n, s, chunk) == (windows - randomised, seed, tw.RANGE_CHUNK) and world is not ws.vary
        scene, effects = world(SCENE, noise_preset("lab", 12), np.random.default_rng(seed))
        assert effects == noise_preset("lab", 12) and 4.0 <= scene.light.angle_deg <= 10.15
        assert scene.light.azimuth_deg == SCENE.light.azimuth_deg  # identified: the calibrated value
    if randomised:
        n, s, _, world = asked.pop("randomised")
        assert (n, s) == (randomised, seed + tw.RANDOMISED_SEEDS) and world is not ws.vary
    assert not asked


@settings(max_examples=30, deadline=None)
@given(windows=st.integers(0, 400), randomised=st.integers(0, 400), seed=st.integers(0, 10**6))
def test_calibration_windows_over_open_ranges_come_from_worlds_at_seeds_no_other_window_uses(
    windows: int, randomised: int, seed: int
) -> None:
    """With a calibration's ``ranges``, the scene's own calibration windows of each camera come from
    :data:`training.window.CALIBRATION_WORLDS` worlds drawn over them, as the randomised ones do, and no two
    recordings, of calibration or training (:func:`training.window.render_mix` at the scene's seeds, as each
    chunk of :func:`training.window_scenes.render_randomised` is), share a seed."""
    asked: list[tuple[int, int, str, object]] = []

    def render(
        folder: Path, scene: Scene, n: int, s: int, motion: object, name: str, bits: int, vary: object = None
    ) -> list[Path]:
        asked.append((n, s, name, vary))
        return [folder / f"{name}-{noise}-{s + k}.cine" for k, noise in enumerate(tw.TRAINING_NOISE)]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(tw, "render_training", render)
        tw.render_calibration(Path("data"), SCENE, windows, seed, randomised, OPEN)
    own = [(n, v) for n, _, name, v in asked if not name.startswith("calibrate-randomised")]
    assert sum(n for n, _ in own) == 2 * windows and len(own) <= 2 * tw.CALIBRATION_WORLDS
    assert all(v is not None and v is not ws.vary for _, v in own)
    used = [s + k for _, s, *_ in asked for k in range(len(tw.TRAINING_NOISE))]
    mix = {
        o + k
        for o in (0, tw.EIGHT_BIT_SEEDS, tw.NOMINAL_SEEDS, tw.NOMINAL_SEEDS + tw.EIGHT_BIT_SEEDS)
        for k in (0, 1, 2)
    }
    assert len(used) == len(set(used)) and not {seed + m for m in mix} & set(used)
    assert all(s < seed + ws.CHUNK_SEEDS for s in used)  # below the second chunk of training windows
