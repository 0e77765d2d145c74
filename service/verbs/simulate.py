"""``meniscope simulate``: a synthetic recording with ejections and its ground truth (shared/spec/cli.md)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from service.errors import MeniscopeError
from service.noise_presets import NOISE_PRESETS
from service.verbs import add_scene_option

#: The most sun directions ``--sun-samples`` takes (as the simulated camera source, ``sim://``).
MAX_SUN_SAMPLES = 64


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="render a synthetic recording with ejections and write its ground truth",
        description="Render a synthetic recording (.cine or .avi, by extension) with ejections and damped "
        "oscillations between them; write REC.truth.json beside it.",
    )
    add_scene_option(p)
    p.add_argument("--out", type=Path, required=True, help="recording to write: REC.cine or REC.avi")
    p.add_argument("--windows", type=int, default=10, help="windows between ejections (default 10)")
    p.add_argument("--seed", type=int, default=0, help="seed of the motion and the noise (default 0)")
    p.add_argument("--ejection-hz", type=float, default=100.0, help="ejections per second (default 100)")
    p.add_argument(
        "--bit-depth", type=int, help="stored bits per pixel: 8, 12 or 16 for .cine (default 12); .avi stores 8 only"
    )
    p.add_argument(
        "--noise",
        choices=[*NOISE_PRESETS, "scene"],
        help="camera: a preset of full well, read noise, blur, black level, or 'scene' for the scene "
        "file's calibrated sensor block (default: the scene's sensor if it has one, else lab)",
    )
    p.add_argument(
        "--frame",
        type=_frame_size,
        metavar="WxH",
        help="recorded frame size when larger than the ROI, which sits at camera.roi in it "
        "(default: a frame that ends with the ROI)",
    )
    p.add_argument(
        "--renderer",
        choices=("meniscope", "blender"),
        default="meniscope",
        help="forward renderer: our ray tracer (default) or Blender Cycles, a second renderer that "
        "stands for a real camera the models were not trained on (about 4 frames/s)",
    )
    p.add_argument(
        "--kinds",
        default=None,
        help="window kinds, comma-separated, window k of the k-th modulo their number: nominal, settled, "
        "heavy, light, 4khz, faint, drift, skip, spatter (default: the nominal ranges)",
    )
    p.add_argument("--blender-samples", type=int, default=32, help="Cycles samples per pixel (default 32)")
    p.add_argument(
        "--sun-samples",
        type=int,
        help=f"directions our renderer integrates the sun's disc over, 1-{MAX_SUN_SAMPLES} (default 4; `calibrate` "
        "draws its renders with 24: a test recording for it drawn as it draws)",
    )
    p.set_defaults(func=run)


def _frame_size(text: str) -> tuple[int, int]:
    """``WxH`` as (width, height), both positive."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH (e.g. 128x128), got {text!r}") from None
    if width < 1 or height < 1:
        raise argparse.ArgumentTypeError(f"frame size must be positive, got {text!r}")
    return width, height


def run(args: argparse.Namespace) -> int:
    from service.camera_effects import noise_preset, sensor_effects
    from service.scene import Scene
    from service.simulate import (  # the renderer loads only when a verb needs it
        canvas,
        check_output,
        simulate,
        truth_path,
    )

    if args.windows < 1:
        raise MeniscopeError("--windows", f"must be at least 1, got {args.windows}")
    if not (math.isfinite(args.ejection_hz) and args.ejection_hz > 0):
        raise MeniscopeError("--ejection-hz", f"must be a positive number, got {args.ejection_hz}")
    if args.seed < 0:
        raise MeniscopeError("--seed", f"must be zero or positive, got {args.seed}")
    kinds, names = (), ()
    if args.kinds:
        from service.window_kinds import kinds_named

        try:
            kinds, names = kinds_named(args.kinds), tuple(n.strip() for n in args.kinds.split(","))
        except ValueError as exc:
            raise MeniscopeError("--kinds", str(exc)) from None
    if args.sun_samples is not None:
        if args.renderer == "blender":
            raise MeniscopeError("--sun-samples", "is our renderer's: Blender Cycles samples the sun's disc itself")
        if not 1 <= args.sun_samples <= MAX_SUN_SAMPLES:
            raise MeniscopeError("--sun-samples", f"must be 1 to {MAX_SUN_SAMPLES}, got {args.sun_samples}")
    scene = Scene.load(args.scene)
    bit_depth = args.bit_depth or (8 if args.out.suffix.lower() == ".avi" else 12)
    check_output(args.out, bit_depth)
    shown = canvas(scene, args.frame)[0] if args.frame else scene
    renderer = None
    if args.renderer == "blender":
        from service.render.blender import BlenderRenderer

        renderer = BlenderRenderer(shown, samples=args.blender_samples, seed=args.seed)
    elif args.sun_samples is not None:
        from service.render import Renderer

        renderer = Renderer(shown, sun_samples=args.sun_samples)
    noise = args.noise or ("scene" if scene.sensor else "lab")
    if noise == "scene":
        if scene.sensor is None:
            raise MeniscopeError(args.scene, "--noise scene: the scene has no sensor block (run meniscope calibrate)")
        effects = sensor_effects(**scene.sensor.model_dump(), bit_depth=bit_depth)
    else:
        effects = noise_preset(noise, bit_depth)
    truth = simulate(
        scene,
        args.out,
        windows=args.windows,
        seed=args.seed,
        ejection_hz=args.ejection_hz,
        effects=effects,
        noise=noise,
        renderer=renderer,
        frame=args.frame,
        kinds=kinds,
        kind_names=names,
    )
    rec = truth["recording"]
    print(
        f"{args.out}: {rec['frames']} frames at {rec['fps']:g} fps, {len(truth['windows'])} windows; "
        f"truth in {truth_path(args.out)}"
    )
    return 0
