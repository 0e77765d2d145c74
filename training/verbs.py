"""The offline verbs, added to ``meniscope`` through the ``meniscope.verbs`` entry point: ``dataset``, ``database``,
``train``, ``quantize``.

The nearest-neighbour database (Price et al. 2022, Sec. 3.2 (a)) is a dataset folder: renders with the
coefficients they were made from. ``meniscope database`` renders one apart from the training renders
(seed 1, where ``train`` uses seed 0) and indexes it once to check it; ``meniscope train --dataset DIR``
keeps its training renders in DIR, which is a database too. Model folders stay small (they are committed)
and never hold a database; ``meniscope validate --database DIR`` and the nearest-neighbour methods name it.
"""

from __future__ import annotations

import argparse
import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from service.errors import MeniscopeError
from service.verbs import add_scene_option

if TYPE_CHECKING:
    from service.scene import Scene

#: ``train``'s window model: windows per noise preset it is trained on (half at the nominal motion, half widened,
#: one in ``EIGHT_BIT_SHARE`` of each through the 8-bit camera: ``training.window.render_mix``), its epochs, and
#: the windows per preset and camera (12 and 8 bits: ``training.window.render_calibration``) that calibrate its
#: intervals, with as many more from scenes randomised around the scene (docs/window_model.md: its error fell with
#: the windows trained on; the intervals held on Blender's camera with the randomised ones).
WINDOW_WINDOWS, WINDOW_EPOCHS, WINDOW_CALIBRATION = 2100, 80, 80
#: Top-level modules of the train extra -> the extra (the scale extra's Dask is checked where --scheduler is read).
EXTRA_OF = {"torch": "train", "onnx": "train"}


def _needs_extras(run: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """``run``, with a module of a missing extra reported as one line saying how to install it.

    The verbs are listed after a runtime-only install too (training/ is in the package), so their
    libraries load only when one runs, and a missing one must say which extra brings it.
    """

    @functools.wraps(run)
    def checked(args: argparse.Namespace) -> int:
        try:
            return run(args)
        except ModuleNotFoundError as exc:
            module = (exc.name or "").split(".")[0]
            if module not in EXTRA_OF:
                raise
            extra = EXTRA_OF[module]
            raise MeniscopeError(
                None,
                f"needs {module} (meniscope's {extra} extra), not installed here: in the "
                f"checkout run `bash deploy/install.sh --dev`, or `pip install -e '.[{extra}]'` with "
                "meniscope's environment's pip",
            ) from None

    return checked


def _render_options(p: argparse.ArgumentParser, seed: int) -> None:
    """The options of a folder of renders (``dataset`` and ``database``): scene, size, seed, workers, storage."""
    add_scene_option(p)
    p.add_argument("--out", type=Path, required=True, help="folder to create (new or empty)")
    p.add_argument("--samples", type=int, default=20000, help="frames to render (default 20000)")
    p.add_argument(
        "--seed", type=int, default=seed, help=f"seed (default {seed}); the files do not depend on --workers"
    )
    p.add_argument(
        "--workers",
        type=int,
        default=os.cpu_count() or 1,
        help="processes rendering chunks (default: one per CPU core)",
    )
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="render the chunks on the Dask cluster of this scheduler (tcp://host:8786) instead of local "
        "processes; needs the scale extra here and meniscope on every worker",
    )
    p.add_argument(
        "--chunk-size", type=int, default=2048, help="frames per chunk and per jittered scene (default 2048)"
    )
    p.add_argument("--bit-depth", type=int, default=8, help="stored bits: 8 (uint8) or 10, 12, 16 (uint16); default 8")


def _open_ranges_option(p: argparse.ArgumentParser, what: str) -> None:
    """``--open-ranges``: render over what the scene's calibration left open (its report beside it)."""
    p.add_argument(
        "--open-ranges",
        action=argparse.BooleanOptionalAction,
        default=False,
        help=f"where SCENE.calibration.json lies beside the scene (made for it by `meniscope calibrate`), render "
        f"{what} with each parameter it leaves open drawn over its range, not at the one value the calibration "
        "wrote (default: off: on the rough fluid B it cost the offset more than it won on the amplitude; "
        "docs/calibration.md)",
    )


def _open_ranges(args: argparse.Namespace, scene: Scene) -> dict[str, tuple[float, float]]:
    """The open ranges ``--open-ranges`` asks for (none without a report made for ``scene``), said in a line."""
    from service.calibration.open_ranges import beside

    ranges = beside(args.scene, scene) if args.open_ranges else {}
    if ranges:
        spans = ", ".join(f"{name} {lo:.4g}-{hi:.4g}" for name, (lo, hi) in ranges.items())
        print(f"rendering over what the calibration left open: {spans}")
    return ranges


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "dataset",
        help="render a training set of random shapes through a randomised camera",
        description="Render SAMPLES frames of random Eq. 1 shapes (jittered scene, randomised camera) into a "
        "memory-mappable folder: frames.npy, coeffs.npy, centre.npy, manifest.json.",
    )
    _render_options(p, seed=0)
    _open_ranges_option(p, "the frames")
    p.set_defaults(func=run, index=False)

    p = subparsers.add_parser(
        "database",
        help="render the nearest-neighbour database (renders with their coefficients) and index it",
        description="Render SAMPLES frames as `meniscope dataset` does, seeded apart from the training renders, "
        "then build the exact and approximate (PCA + FLANN) search index once to check it. The paper compares "
        "20,000 and 100,000 renders.",
    )
    _render_options(p, seed=1)
    _open_ranges_option(p, "the frames")
    p.set_defaults(func=run, index=True)

    p = subparsers.add_parser(
        "train",
        help="train the inverse models for a scene and export them as ONNX",
        description="Train the VAE on unlabeled lab frames, the regressor on synthetic renders through its "
        "encoder, and the direct CNN baseline; export ONNX graphs, loss and validation plots and a manifest "
        "into MODEL_DIR.",
    )
    add_scene_option(p)
    p.add_argument("--lab-video", type=Path, required=True, help="unlabeled lab recording (.cine or .avi)")
    p.add_argument("--out", type=Path, required=True, help="model folder to write (new or empty)")
    p.add_argument("--samples", type=int, help="synthetic renders to train on (default 50000; --quick 1536)")
    p.add_argument(
        "--dataset",
        type=Path,
        help="a dataset folder from `meniscope dataset` to use (or create, and keep: it then serves as the "
        "nearest-neighbour database too)",
    )
    p.add_argument("--holdout", type=Path, help="a simulated recording (with .truth.json) no model sees, scored")
    p.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    p.add_argument(
        "--input-px",
        type=int,
        help="model input height after in-graph pooling (default 32: the ROI "
        "pooled 3x3; 48 pools 2x2, slower and sees finer highlights); must divide the ROI",
    )
    p.add_argument(
        "--channels",
        help="the convolutional trunk's channels, one stride-2 3x3 convolution per entry, comma-separated (default "
        "8,16,32; more: a dearer graph per frame, measured in docs/benchmarks.md)",
    )
    p.add_argument(
        "--init",
        type=Path,
        metavar="MODELS",
        help="fine-tune: start from the weights of this model folder (made for any scene with the same ROI and "
        "network sizes, e.g. models/default) with a fifth of the renders and a quarter of the epochs",
    )
    p.add_argument("--quick", action="store_true", help="a run of seconds for tests; its models are not useful")
    _open_ranges_option(p, "the training frames and windows")
    p.add_argument(
        "--window-windows",
        type=int,
        help=f"windows per noise preset the window model is trained on (default {WINDOW_WINDOWS}; --quick 2; 0: no "
        f"window model), rendered by our renderer from the scene; {WINDOW_CALIBRATION} more per preset at 12 and 8 bits, "
        f"and {WINDOW_CALIBRATION} from scenes randomised around it, calibrate its intervals",
    )
    p.set_defaults(func=run_train)

    p = subparsers.add_parser(
        "quantize",
        help="write an int8 copy of a model folder, with its parity against the float one",
        description="Quantise the inverse graphs of MODELS (the convolutions after the first) to int8 with "
        "onnxruntime into OUT, and record in OUT's manifest how, and how far the int8 outputs lie from the float "
        "ones on renders no model saw. Serve or bench it like any model folder (--models OUT).",
    )
    add_scene_option(p)
    p.add_argument("--models", type=Path, required=True, help="the float model folder (`meniscope train`)")
    p.add_argument("--out", type=Path, required=True, help="model folder to write (new or empty)")
    p.add_argument(
        "--mode",
        choices=["static", "dynamic"],
        default="static",
        help="static: activation ranges calibrated on renders, fast on the CPU (default); dynamic: "
        "ranges measured per batch at run time",
    )
    p.add_argument("--calibration", type=int, default=512, help="renders the static ranges come from (default 512)")
    p.add_argument(
        "--parity", type=int, default=512, help="renders the int8 and float outputs are compared on (default 512)"
    )
    p.set_defaults(func=run_quantize)


@_needs_extras
def run_train(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from service.scene import Scene
    from training.normalise import downsample_factor  # torch loads only when the verb runs
    from training.train import TrainConfig, train_models
    from training.warmstart import net_of

    scene = Scene.load(args.scene)
    ranges = _open_ranges(args, scene)
    if args.quick:
        config = replace(TrainConfig.quick(), init=None if args.init is None else str(args.init))
    else:
        config = TrainConfig() if args.init is None else TrainConfig.fine_tune(args.init)
    if args.init is not None:  # its network sizes, which a warm start keeps
        config = replace(config, net=net_of(args.init))
    if args.samples is not None:
        if args.samples < 64:
            raise MeniscopeError("--samples", f"must be at least 64, got {args.samples}")
        config = replace(config, samples=args.samples)
    if args.seed < 0:
        raise MeniscopeError("--seed", f"must be zero or positive, got {args.seed}")
    config = replace(config, seed=args.seed, open_ranges=ranges)
    if args.input_px is not None:
        try:
            downsample_factor(scene, args.input_px)
        except MeniscopeError as exc:
            raise MeniscopeError("--input-px", exc.problem) from None
        config = replace(config, net=replace(config.net, input_px=args.input_px))
    if args.channels is not None:
        config = replace(config, net=replace(config.net, channels=_channels(args.channels)))
    manifest = train_models(scene, args.lab_video, args.out, config, dataset=args.dataset, holdout_video=args.holdout)
    print(f"{args.out}: {', '.join(sorted(manifest.methods))} exported in {manifest.training.seconds:.0f} s")
    _train_window_model(args, scene, ranges)
    for name, by_data in manifest.validation.items():
        for data, s in by_data.items():
            rmse = ", ".join(f"{k} {v:.3g}" for k, v in s.rmse.items())
            r = "n/a" if s.centre_correlation is None else f"{s.centre_correlation:.3f}"
            print(f"  {name} on {data} ({s.frames} frames): RMSE {rmse}; D(0, t) correlation {r}")
    return 0


def _channels(text: str) -> tuple[int, ...]:
    """``--channels``' comma-separated counts, each a whole number of at least 1."""
    try:
        channels = tuple(int(c) for c in text.split(","))
    except ValueError:
        raise MeniscopeError("--channels", f"must be whole numbers separated by commas, got {text!r}") from None
    if min(channels) < 1:
        raise MeniscopeError("--channels", f"each must be at least 1, got {text!r}")
    return channels


def _train_window_model(args: argparse.Namespace, scene: Scene, ranges: dict[str, tuple[float, float]]) -> None:
    """The window model of the network just trained (:func:`training.window.build`), its windows rendered in a
    temporary folder (over the calibration's open ``ranges``): what the default method needs beside the network."""
    import tempfile
    import time

    from training.window import build

    windows = args.window_windows if args.window_windows is not None else (2 if args.quick else WINDOW_WINDOWS)
    if windows < 0:
        raise MeniscopeError("--window-windows", f"must be zero or positive, got {windows}")
    if windows == 0:
        return
    started = time.perf_counter()
    epochs, calibration = (2, 0) if args.quick else (WINDOW_EPOCHS, WINDOW_CALIBRATION)
    with tempfile.TemporaryDirectory(prefix="meniscope-window-") as scratch:
        build(args.out, scene, Path(scratch), windows, epochs, args.seed, calibration, ranges=ranges)
    print(f"{args.out}: window model trained in {time.perf_counter() - started:.0f} s")


@_needs_extras
def run_quantize(args: argparse.Namespace) -> int:
    from service.scene import Scene
    from training.quantize import quantize_models  # onnx loads only when the verb runs

    for option, value in (("--calibration", args.calibration), ("--parity", args.parity)):
        if value < 2:
            raise MeniscopeError(option, f"must be at least 2 renders, got {value}")
    manifest = quantize_models(args.models, args.out, Scene.load(args.scene), args.mode, args.calibration, args.parity)
    for name, p in manifest.quantisation.parity.items():
        diffs = ", ".join(f"{k} {v:.3g}" for k, v in p.max_abs.items())
        print(
            f"{args.out}: {name} int8 ({args.mode}); largest |int8 - float| on {p.frames} renders: {diffs}; "
            f"D(0) RMSE {p.float32.rmse['centre']:.4g} -> {p.int8.rmse['centre']:.4g} mm"
        )
    return 0


@_needs_extras
def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from service.scene import Scene
    from training.dataset import DatasetConfig, Jitter, generate  # the renderer loads only when the verb runs

    scene = Scene.load(args.scene)
    jitter = Jitter(open_ranges=_open_ranges(args, scene))
    try:
        config = DatasetConfig(
            scene=scene,
            samples=args.samples,
            seed=args.seed,
            chunk_size=args.chunk_size,
            bit_depth=args.bit_depth,
            jitter=jitter,
        )
    except ValidationError as exc:
        err = exc.errors()[0]
        raise MeniscopeError(
            f"--{str(err['loc'][0]).replace('_', '-')}", f"{err['msg']}, got {err['input']!r}"
        ) from None
    manifest = generate(config, args.out, workers=args.workers, scheduler=args.scheduler)
    frames = manifest["frames"]
    print(
        f"{args.out}: {manifest['samples']} frames {frames['dtype']} {frames['shape'][1]}x{frames['shape'][2]} "
        f"in {manifest['chunks']} chunks"
    )
    if args.index:
        import time

        from service.inverse.nearest import NearestDatabase

        started = time.perf_counter()
        database = NearestDatabase.load(args.out)
        print(f"{args.out}: indexed {len(database)} renders in {time.perf_counter() - started:.1f} s")
    return 0
