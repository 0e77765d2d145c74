"""The offline verbs, added to ``meniscope`` through the ``meniscope.verbs`` entry point: ``dataset``."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from service import DEFAULT_SCENE
from service.errors import MeniscopeError
from service.scene import Scene


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "dataset",
        help="render a training set of random shapes through a randomised camera",
        description="Render SAMPLES frames of random Eq. 1 shapes (jittered scene, randomised camera) into a "
        "memory-mappable folder: frames.npy, coeffs.npy, centre.npy, manifest.json.",
    )
    p.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="scene file (default: the embedded one)")
    p.add_argument("--out", type=Path, required=True, help="dataset folder to create (new or empty)")
    p.add_argument("--samples", type=int, default=20000, help="frames to render (default 20000)")
    p.add_argument("--seed", type=int, default=0, help="seed (default 0); the files do not depend on --workers")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                   help="processes rendering chunks (default: one per CPU core)")
    p.add_argument("--chunk-size", type=int, default=2048, help="frames per chunk and per jittered scene (default 2048)")
    p.add_argument("--bit-depth", type=int, default=8, help="stored bits: 8 (uint8) or 10, 12, 16 (uint16); default 8")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from training.dataset import DatasetConfig, generate  # the renderer loads only when the verb runs

    scene = Scene.load(args.scene)
    try:
        config = DatasetConfig(scene=scene, samples=args.samples, seed=args.seed, chunk_size=args.chunk_size,
                               bit_depth=args.bit_depth)
    except ValidationError as exc:
        err = exc.errors()[0]
        raise MeniscopeError(f"--{str(err['loc'][0]).replace('_', '-')}", f"{err['msg']}, got {err['input']!r}") from None
    manifest = generate(config, args.out, workers=args.workers)
    frames = manifest["frames"]
    print(f"{args.out}: {manifest['samples']} frames {frames['dtype']} {frames['shape'][1]}x{frames['shape'][2]} "
          f"in {manifest['chunks']} chunks")
    return 0
