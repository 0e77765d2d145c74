"""``meniscope simulate``: a synthetic recording with ejections and its ground truth (shared/spec/cli.md)."""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from service.verbs import add_scene_option
from service.camera_effects import NOISE_PRESETS, noise_preset
from service.errors import MeniscopeError


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
    p.add_argument("--bit-depth", type=int,
                   help="stored bits per pixel: 8, 12 or 16 for .cine (default 12); .avi stores 8 only")
    p.add_argument("--noise", choices=list(NOISE_PRESETS), default="lab",
                   help="camera preset: full well, read noise, blur, black level (default lab)")
    p.add_argument("--renderer", choices=("meniscope", "blender"), default="meniscope",
                   help="forward renderer: our ray tracer (default) or Blender Cycles, a second renderer that "
                   "stands for a real camera the models were not trained on (about 4 frames/s)")
    p.add_argument("--kinds", default=None,
                   help="window kinds, comma-separated, window k of the k-th modulo their number: nominal, settled, "
                   "heavy, light, 4khz, faint, drift, skip, spatter (default: the nominal ranges)")
    p.add_argument("--blender-samples", type=int, default=32, help="Cycles samples per pixel (default 32)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from service.scene import Scene

    from service.simulate import check_output, simulate, truth_path  # the renderer loads only when a verb needs it

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
    scene = Scene.load(args.scene)
    bit_depth = args.bit_depth or (8 if args.out.suffix.lower() == ".avi" else 12)
    check_output(args.out, bit_depth)
    renderer = None
    if args.renderer == "blender":
        from service.render.blender import BlenderRenderer

        renderer = BlenderRenderer(scene, samples=args.blender_samples, seed=args.seed)
    truth = simulate(scene, args.out, windows=args.windows, seed=args.seed, ejection_hz=args.ejection_hz,
                     effects=noise_preset(args.noise, bit_depth), noise=args.noise, renderer=renderer,
                     kinds=kinds, kind_names=names)
    rec = truth["recording"]
    print(f"{args.out}: {rec['frames']} frames at {rec['fps']:g} fps, {len(truth['windows'])} windows; "
          f"truth in {truth_path(args.out)}")
    return 0
