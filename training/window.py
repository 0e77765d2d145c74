"""Training of the window model (:mod:`service.inverse.window_model`) on simulated recordings, and its export.

Each recording (``meniscope simulate``: frames and their truth) is replayed through the pipeline's own per-frame
stages with the model folder's network, exactly as ``meniscope analyze`` and ``serve`` see it; each true window
gives one example: its features in, the correction that takes its steady D(0, t) to the true one out (scored on
the oscillating frames only). Usage::

    python -m training.window --models models/default REC1.cine REC2.cine ...
"""

from __future__ import annotations

import argparse
import io
import json
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import onnx
import torch
from torch import nn
from tqdm import tqdm

from service import DEFAULT_MODELS, DEFAULT_SCENE
from service.analysis.results import FitSettings
from service.analysis.steady import window_steady_centre
from service.inverse import window_model as wm
from service.inverse.manifest import MANIFEST, Manifest, sha256_file, write_manifest
from service.inverse.methods import open_method
from service.pipeline.records import FRAME, coefficients_of
from service.pipeline.stages import FrameStages
from service.scene import Scene
from service.simulate import WindowRanges
from service.sources.replay import ReplaySource
from service.validation.truth import read_truth, truth_centre

if TYPE_CHECKING:
    from service.camera_effects import CameraEffects

OPSET = 17


@dataclass(frozen=True)
class Examples:
    """Windows padded to one length: features (W, channels, m) (:data:`wm.FEATURE_NAMES`, then the network's
    :data:`wm.LATENT_FEATURES` where it has them), targets (W, m) (the correction, SCALE_MM units) and which frames are
    scored (W, m): the oscillating frames with values."""

    features: np.ndarray
    targets: np.ndarray
    scored: np.ndarray

    def select(self, windows: np.ndarray) -> Examples:
        """These examples' ``windows`` (indices)."""
        return Examples(self.features[windows], self.targets[windows], self.scored[windows])

    def without_latent(self) -> Examples:
        """These examples' :data:`wm.FEATURES` channels alone: a model that does not take the latent."""
        return Examples(self.features[:, : wm.FEATURES], self.targets, self.scored)


#: The motion of the training windows: the simulator's ranges (:class:`service.simulate.WindowRanges`) widened down
#: to windows that barely move or settle within a few periods, which the live service sees too (a model never
#: shown one makes up an oscillation there).
TRAINING_RANGES = WindowRanges(A1=(0.0, 0.025), A2=(0.0, 0.012), g1=(100.0, 5000.0))
#: Camera noise presets the training windows are rendered at, so that the model holds at each.
TRAINING_NOISE = ("low", "lab", "high")
#: A recording's world drawn from the scene and the noise preset's camera (:func:`training.window_scenes.vary`).
Vary = Callable[[Scene, "CameraEffects", np.random.Generator], tuple[Scene, "CameraEffects"]]


def render_training(
    folder: Path,
    scene: Scene,
    windows: int,
    seed: int,
    ranges: WindowRanges = TRAINING_RANGES,
    name: str = "window",
    bit_depth: int = 12,
    vary: Vary | None = None,
) -> list[Path]:
    """Recordings of ``windows`` windows each at every :data:`TRAINING_NOISE` preset (``bit_depth`` bits, our
    renderer, motion from ``ranges``), written to ``folder`` (kept: reused when there) with their truth. One
    renderer serves them all (its set-up costs as much as thousands of frames), unless ``vary`` draws each
    recording's scene and camera (seeded by the recording's seed), written beside it (``REC.world.json``)."""
    from service.camera_effects import noise_preset
    from service.render import Renderer
    from service.simulate import simulate, truth_path

    folder.mkdir(parents=True, exist_ok=True)
    paths, renderer = [], None
    for k, noise in enumerate(TRAINING_NOISE):
        path = folder / f"{name}-{noise}-{seed + k}.cine"
        if not truth_path(path).exists():
            world, effects = scene, noise_preset(noise, bit_depth)
            if vary:
                world, effects = vary(scene, effects, np.random.default_rng([VARY_KEY, seed + k]))
                record = {"scene": world.model_dump(mode="json"), "effects": effects.model_dump(mode="json")}
                path.with_name(path.name + ".world.json").write_text(json.dumps(record, indent=1) + "\n")
            renderer = Renderer(world) if vary or renderer is None else renderer
            simulate(
                world,
                path,
                windows=windows,
                seed=seed + k,
                effects=effects,
                noise=noise,
                ranges=ranges,
                renderer=renderer,
            )
        paths.append(path)
    return paths


#: Mixed into a varied recording's seed for its world's draw, so that it is not its motion's.
VARY_KEY = 17


def recording_records(path: Path, scene: Scene, models: Path) -> np.ndarray:
    """Every frame's record of a recording, replayed through the pipeline's per-frame stages and ``models``' network."""
    method, _ = open_method("network", scene, models)
    parts = []
    with ReplaySource(path, speed=0.0) as source:
        stages = FrameStages(scene, source.format, str(path), method)
        while (batch := source.read(512)) is not None:
            batch = stages.roi(batch)
            records, inputs = stages.measure(batch)
            parts.append(stages.infer(inputs, records))
    return np.concatenate(parts) if parts else np.empty(0, FRAME)


def recording_examples(path: Path, scene: Scene, models: Path, settings: FitSettings = FitSettings()) -> Examples:
    """One example per true window of a simulated recording, with the network's latent where it outputs one."""
    truth = read_truth(path)
    records = recording_records(path, scene, models)
    latent = records["latent"] if np.isfinite(records["latent"]).any() else None
    true = truth_centre(truth)
    fps, radius = truth["recording"]["fps"], scene.nozzle.radius_mm
    skip = settings.transient_frames(fps)
    feats, targets, scored = [], [], []
    for w in truth["windows"]:
        lo, hi = w["start_frame"], w["end_frame"]
        r = records[lo:hi]
        coefficients = coefficients_of(r)
        steady = window_steady_centre(coefficients, radius, skip, True)
        f = wm.window_features(coefficients, r["brightness"], steady, skip, None if latent is None else latent[lo:hi])
        feats.append(f)
        targets.append(np.nan_to_num((true[lo:hi] - steady) / wm.SCALE_MM).astype(np.float32))
        keep = f[wm.PRESENT] > 0
        keep[: w["oscillation_start_frame"] - lo] = False
        scored.append(keep)
    return pad(feats, targets, scored)


def cached_examples(path: Path, scene: Scene, models: Path) -> Examples:
    """:func:`recording_examples`, kept beside the recording (``REC.window-examples.npz``) and reused while the
    per-frame network it came from is the same."""
    cache = path.with_name(path.name + ".window-examples.npz")
    network = sha256_file(models / wm.NETWORK)
    if cache.is_file():
        with np.load(cache) as stored:
            if str(stored["network_sha256"]) == network:
                return Examples(stored["features"], stored["targets"], stored["scored"])
    examples = recording_examples(path, scene, models)
    np.savez(cache, network_sha256=network, **examples.__dict__)
    return examples


def pad(feats: list[np.ndarray], targets: list[np.ndarray], scored: list[np.ndarray]) -> Examples:
    """Windows of different lengths zero-padded (not scored) to the longest."""
    m = max(f.shape[1] for f in feats)
    out = Examples(
        np.zeros((len(feats), feats[0].shape[0], m), np.float32),
        np.zeros((len(feats), m), np.float32),
        np.zeros((len(feats), m), bool),
    )
    for i, (f, t, s) in enumerate(zip(feats, targets, scored)):
        out.features[i, :, : f.shape[1]], out.targets[i, : t.size], out.scored[i, : s.size] = f, t, s
    return out


def concat(parts: list[Examples]) -> Examples:
    """Examples of several recordings together."""
    return pad(
        [f[:, : s.size] for p in parts for f, s in zip(p.features, p.scored)],
        [t for p in parts for t in p.targets],
        [s for p in parts for s in p.scored],
    )


class WindowNet(nn.Module):
    """Dilated residual 1-D convolutions over the window's frames (a receptive field of the whole window), each
    block also fed the mean of the window's present frames (what holds for the whole window: its amplitude,
    the shrink of its per-frame estimates)."""

    def __init__(
        self, features: int = wm.FEATURES, width: int = 48, dilations: tuple[int, ...] = (1, 2, 4, 8, 16, 32)
    ) -> None:
        super().__init__()
        self.inp = nn.Conv1d(features, width, 1)
        self.convs = nn.ModuleList(nn.Conv1d(width, width, 5, dilation=d, padding=2 * d) for d in dilations)
        self.context = nn.ModuleList(nn.Linear(width, width) for _ in dilations)
        self.out = nn.Conv1d(width, 1, 1)
        nn.init.zeros_(self.out.weight)  # starts as the steady series itself
        nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        present = x[:, wm.PRESENT : wm.PRESENT + 1]
        count = present.sum(-1).clamp(min=1.0)
        h = self.inp(x)
        for conv, context in zip(self.convs, self.context):
            mean = (h * present).sum(-1) / count
            h = h + nn.functional.gelu(conv(h) + context(mean)[..., None])
        return self.out(h)[:, 0]


def train(train_set: Examples, check: Examples, epochs: int = 300, seed: int = 0) -> tuple[WindowNet, list[float]]:
    """The net (taking ``train_set``'s channels) with the lowest scored MSE on ``check`` over ``epochs`` of Adam on
    ``train_set``; check losses."""
    torch.manual_seed(seed)
    net = WindowNet(train_set.features.shape[1])
    opt = torch.optim.AdamW(net.parameters(), 2e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    x, y, s = (torch.from_numpy(a) for a in (train_set.features, train_set.targets, train_set.scored))
    cx, cy, cs = (torch.from_numpy(a) for a in (check.features, check.targets, check.scored))
    best, best_state, history = np.inf, None, []
    rng = np.random.default_rng(seed)
    for _ in tqdm(range(epochs), desc="window model", unit="epoch"):
        net.train()
        for batch in np.array_split(rng.permutation(len(x)), max(1, len(x) // 32)):
            loss = ((net(x[batch]) - y[batch]) ** 2)[s[batch]].mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
        net.eval()
        with torch.no_grad():
            value = float(((net(cx) - cy) ** 2)[cs].mean())
        history.append(value)
        if value < best:
            best, best_state = value, {k: v.clone() for k, v in net.state_dict().items()}
    net.load_state_dict(best_state)
    return net.eval(), history


def export(net: WindowNet, path: Path) -> None:
    """``net`` as an ONNX graph features (1, channels, m) -> correction (1, m), m dynamic, weights inside."""
    buffer = io.BytesIO()
    example = torch.zeros(1, net.inp.in_channels, 190)
    with warnings.catch_warnings():  # the TorchScript exporter's deprecation notices (see training.export)
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            net,
            (example,),
            buffer,
            input_names=[wm.INPUT],
            output_names=[wm.OUTPUT],
            dynamic_axes={wm.INPUT: {2: "frames"}, wm.OUTPUT: {1: "frames"}},
            opset_version=OPSET,
            dynamo=False,
        )
    model = onnx.load_from_string(buffer.getvalue())
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


#: Whether :func:`build` gives the model the per-frame network's latent (where the network outputs it) besides the
#: other channels: not by default, since with it the A/B's model was better on our renderer but not on Blender's
#: recordings (docs/window_model.md, "The per-frame network's latent as input").
LATENT_INPUT = False
#: Seeds of the calibration windows lie this far above the training windows' (other motions, other noise).
CALIBRATION_SEEDS = 100
#: Seeds of the training windows at the simulator's nominal motion lie this far above the widened ones'.
NOMINAL_SEEDS = 200
#: Seeds of the windows from randomised scenes (:func:`training.window_scenes.render_randomised`) start this far
#: above the training windows' (in a folder of their own).
RANDOMISED_SEEDS = 1000
#: One training window in this many (of each half, nominal and widened) is recorded through the 8-bit camera, at seeds
#: :data:`EIGHT_BIT_SEEDS` above its half's 12-bit ones.
EIGHT_BIT_SHARE, EIGHT_BIT_SEEDS = 4, 50
#: The cameras the calibration windows are recorded through: 12 and 8 bits (the 8-bit camera's windows have
#: errors of their own; calibrated on 12-bit windows alone the offset's intervals held the truth in fewer of
#: Blender's windows: docs/window_model.md, "Coverage after the polynomial brightness").
CALIBRATION_BIT_DEPTHS = (12, 8)
#: The calibration windows of a preset and camera from scenes randomised around the scene (:func:`build` pools as
#: many as the scene's own by default) come from this many worlds (recordings) of their own, at seeds from
#: :data:`RANDOMISED_CALIBRATION_SEEDS` above the training windows' (below the nominal ones').
CALIBRATION_WORLDS, RANDOMISED_CALIBRATION_SEEDS = 8, 110
#: Seeds of the scene's own calibration windows where a calibration's open ranges are drawn over (from
#: :data:`CALIBRATION_WORLDS` worlds, so past the randomised ones' and the nominal training windows').
RANGE_CALIBRATION_SEEDS = 300
#: Training windows per preset in each chunk of worlds drawn over a calibration's open ranges (:func:`build`): a
#: world per recording, 12 recordings a chunk, each with a renderer set up for it (seconds of CPU).
RANGE_CHUNK = 150


def render_mix(data: Path, scene: Scene, windows: int, seed: int, vary: Vary | None = None) -> list[Path]:
    """``windows`` training windows per noise preset: half at the simulator's nominal motion (what the held-out
    recordings and the calibration are), half at the widened :data:`TRAINING_RANGES` (windows that barely move or
    settle), one in :data:`EIGHT_BIT_SHARE` of each half through the 8-bit camera. Trained on the widened ones alone
    the model's held-out amplitude error was larger, on 12-bit ones alone its series was biased through an 8-bit
    camera (docs/window_model.md). ``vary``: each recording's own scene and camera (:func:`render_training`)."""
    nominal = windows // 2
    halves = (
        (windows - nominal, seed, TRAINING_RANGES, "window"),
        (nominal, seed + NOMINAL_SEEDS, WindowRanges(), "nominal"),
    )
    paths: list[Path] = []
    for count, first, ranges, name in halves:
        eight = count // EIGHT_BIT_SHARE
        if count > eight:
            paths += render_training(data, scene, count - eight, first, ranges, name, vary=vary)
        if eight:
            paths += render_training(data, scene, eight, first + EIGHT_BIT_SEEDS, ranges, f"{name}-8bit", 8, vary)
    return paths


def render_calibration(
    data: Path,
    scene: Scene,
    windows: int,
    seed: int,
    randomised: int = 0,
    ranges: Mapping[str, tuple[float, float]] | None = None,
) -> list[Path]:
    """``windows`` calibration windows per noise preset and :data:`CALIBRATION_BIT_DEPTHS` camera, at the
    simulator's nominal motion, at seeds from ``seed + CALIBRATION_SEEDS`` on that no training window uses; and
    ``randomised`` more per preset and camera from :data:`CALIBRATION_WORLDS` scenes randomised around ``scene``
    (:func:`training.window_scenes.vary`), at seeds from ``seed + RANDOMISED_CALIBRATION_SEEDS``. ``ranges``: the
    parameters a calibration left open, drawn over their ranges (:func:`service.calibration.open_ranges.drawn_over`) in
    every window's world, the scene's own windows then from :data:`CALIBRATION_WORLDS` worlds too."""
    from training.window_scenes import around, over_ranges

    own = (over_ranges(ranges), RANGE_CALIBRATION_SEEDS) if ranges else (None, CALIBRATION_SEEDS)
    kinds = (
        (windows, *own, "calibrate"),
        (randomised, around(ranges or {}), RANDOMISED_CALIBRATION_SEEDS, "calibrate-randomised"),
    )
    paths = []
    for k, bits in enumerate(CALIBRATION_BIT_DEPTHS):
        for count, world, seeds, name in kinds:
            worlds = 1 if world is None else CALIBRATION_WORLDS
            for j, part in enumerate(p for p in np.array_split(np.arange(count), worlds) if len(p)):
                first = seed + seeds + (k * worlds + j) * len(TRAINING_NOISE)
                paths += render_training(
                    data, scene, len(part), first, WindowRanges(), f"{name}-{bits}bit", bits, world
                )
    return paths


def build(
    models: Path,
    scene: Scene,
    data: Path,
    windows: int,
    epochs: int,
    seed: int,
    calibration: int,
    recordings: tuple[Path, ...] = (),
    latent: bool = LATENT_INPUT,
    randomised: int = 0,
    calibration_randomised: int | None = None,
    ranges: Mapping[str, tuple[float, float]] | None = None,
) -> dict:
    """The window model of ``models``' network: ``windows`` training windows per noise preset rendered into ``data``
    (:func:`render_mix`; with ``recordings``), ``randomised`` of them from scenes randomised around ``scene``
    (:func:`training.window_scenes.render_randomised`, replayed through ``scene``'s network as a recording of the
    real set-up is), trained, exported beside the network with its record, and its intervals calibrated on
    ``calibration`` other windows per preset and camera and ``calibration_randomised`` (None: as many) from scenes
    randomised around ``scene`` (:func:`render_calibration`; none at all: the fit's own intervals stay); the folder's
    manifest rewritten. The randomised windows make the intervals hold on a camera whose world is not the scene's
    (docs/window_model.md, "Intervals calibrated on randomised worlds"). ``latent``: the model takes the network's
    latent per frame too (where the network outputs one). ``ranges``: what the scene's calibration left open
    (:mod:`service.calibration.open_ranges`), drawn over in every window's world (the scene's own windows then in
    chunks of :data:`RANGE_CHUNK` per preset, a world per recording). Returns the record."""
    from training.window_intervals import calibrate_folder

    if not 0 <= randomised <= windows:
        raise ValueError(f"randomised windows ({randomised}) must lie between 0 and the windows ({windows})")
    calibration_randomised = calibration if calibration_randomised is None else calibration_randomised
    if min(calibration, calibration_randomised) < 0:
        raise ValueError(
            f"calibration windows ({calibration}, {calibration_randomised} randomised) must not be negative"
        )
    from training.window_scenes import around, over_ranges, render_randomised

    own, recordings = windows - randomised, tuple(recordings)
    if own:
        recordings += tuple(
            render_randomised(data / "over-ranges", scene, own, seed, RANGE_CHUNK, over_ranges(ranges))
            if ranges
            else render_mix(data, scene, own, seed)
        )
    if randomised:
        world = around(ranges or {})
        recordings += tuple(
            render_randomised(data / "randomised", scene, randomised, seed + RANDOMISED_SEEDS, 40, world)
        )
    if not recordings:
        raise ValueError("no training recordings: render some windows or name recordings")
    examples = concat([cached_examples(r, scene, models) for r in tqdm(recordings, desc="replay")])
    if not latent:
        examples = examples.without_latent()
    order = np.random.default_rng(seed).permutation(len(examples.features))
    held = order[: max(1, len(order) // 10)]
    rest = order[len(held) :]
    net, history = train(examples.select(rest), examples.select(held), epochs, seed)
    baseline = float((examples.targets[held] ** 2)[examples.scored[held]].mean())
    print(f"{len(rest)} windows trained on, {len(held)} checked: scored MSE {min(history):.4g} (steady {baseline:.4g})")
    export(net, models / wm.FILE)
    record = {
        "network_sha256": sha256_file(models / wm.NETWORK),
        "features": list(wm.FEATURE_NAMES + wm.LATENT_FEATURES)[: examples.features.shape[1]],
        "recordings": [str(r) for r in recordings],
        "windows_trained": int(len(rest)),
        "windows_checked": int(len(held)),
        "epochs": epochs,
        "seed": seed,
        "randomised_windows": randomised,
        "open_ranges": {name: list(span) for name, span in (ranges or {}).items()},
        "check_mse": float(min(history)),
        "check_mse_steady": baseline,
    }
    (models / wm.RECORD).write_text(json.dumps(record, indent=1) + "\n")
    # the folder's manifest lists every file with its sha256: the window model's two files too
    write_manifest(models, Manifest.model_validate_json((models / MANIFEST).read_text()))
    if calibration or calibration_randomised:
        held_out = render_calibration(data, scene, calibration, seed, calibration_randomised, ranges)
        intervals = calibrate_folder(models, held_out, scene)
        record["intervals"] = intervals.as_record()
        print(f"intervals calibrated on {intervals.windows} windows: factors {intervals.factor}")
    return record


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m training.window", description=__doc__.splitlines()[0])
    p.add_argument("recordings", nargs="*", type=Path, help="simulated recordings (with .truth.json) to train on")
    p.add_argument(
        "--render",
        type=int,
        default=0,
        metavar="N",
        help="also render N training windows per noise preset (low, lab, high) into --data first",
    )
    p.add_argument(
        "--calibrate",
        type=int,
        default=80,
        metavar="N",
        help="calibrate the intervals on N held-out windows per noise preset and camera (12 and 8 bits) rendered "
        "into --data (0: not, unless --calibrate-randomised)",
    )
    p.add_argument(
        "--calibrate-randomised",
        type=int,
        metavar="N",
        help="and on N more per preset and camera from scenes randomised around --scene (default: as many as "
        "--calibrate; 0: the scene's windows alone)",
    )
    p.add_argument(
        "--randomised",
        type=int,
        default=0,
        metavar="N",
        help="of the --render windows per preset, N from scenes randomised around --scene (training.window_scenes); "
        "--render N --randomised N: the named recordings plus N randomised windows per preset on top",
    )
    p.add_argument("--data", type=Path, default=Path("data/window"), help="folder of the rendered windows")
    p.add_argument("--models", type=Path, default=DEFAULT_MODELS, help="model folder: its network, and the output")
    p.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="scene of the models and the rendered windows")
    p.add_argument("--epochs", type=int, default=300)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--latent",
        action=argparse.BooleanOptionalAction,
        default=LATENT_INPUT,
        help="give the model the per-frame network's latent too (default: %(default)s)",
    )
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    if not args.recordings and not args.render:
        p.error("no recordings: name some or --render N")
    build(
        args.models,
        Scene.load(args.scene),
        args.data,
        args.render,
        args.epochs,
        args.seed,
        args.calibrate,
        tuple(args.recordings),
        args.latent,
        args.randomised,
        args.calibrate_randomised,
    )
    print(f"wrote {args.models / wm.FILE}, {wm.RECORD} and the folder's manifest")


if __name__ == "__main__":
    main()
