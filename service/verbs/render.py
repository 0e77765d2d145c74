"""``meniscope render`` (frames from Eq. 1 coefficients, shared/spec/cli.md) and ``meniscope sheet`` (a PNG of renders)."""

from __future__ import annotations

import argparse
from pathlib import Path

from service.errors import MeniscopeError, require_folder_of
from service.verbs import add_scene_option


def _quality(p: argparse.ArgumentParser) -> None:
    add_scene_option(p)
    p.add_argument("--supersample", type=int, default=2, help="rays per pixel along each axis (default 2)")
    p.add_argument("--sun-samples", type=int, default=4, help="directions over the sun's disc (default 4)")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "render",
        help="render frames from Eq. 1 coefficients",
        description="Render frames of a scene from a CSV of coefficients d,p,a,b (one row "
        "per frame) into FRAMES.npy: float32 (frames, height_px, width_px), linear intensity.",
    )
    _quality(p)
    p.add_argument("--coefficients", type=Path, required=True, help="COEFFS.csv with columns d,p,a,b")
    p.add_argument("--out", type=Path, required=True, help="FRAMES.npy to write")
    p.set_defaults(func=run_render)

    p = subparsers.add_parser(
        "sheet",
        help="PNG sheet of renders across the coefficient ranges",
        description="Write a PNG of renders sweeping each coefficient across its range, and "
        "radial profiles beside their renders.",
    )
    _quality(p)
    p.add_argument("--out", type=Path, default=Path("sheet.png"), help="PNG to write (default sheet.png)")
    p.add_argument("--seed", type=int, default=0, help="seed of the profile draws (default 0)")
    p.set_defaults(func=run_sheet)


def _renderer(args: argparse.Namespace):
    from service.render import Renderer  # the compiled renderer loads only when a verb needs it
    from service.scene import Scene

    return Renderer(Scene.load(args.scene), supersample=args.supersample, sun_samples=args.sun_samples)


def _writable(out: Path, suffix: str) -> None:
    if out.suffix.lower() != suffix:
        raise MeniscopeError(out, f"the output must be a {suffix} file")
    require_folder_of(out)


def run_render(args: argparse.Namespace) -> int:
    import numpy as np

    from service.csvtable import read_columns

    _writable(args.out, ".npy")
    coeffs = read_columns(args.coefficients, ("d", "p", "a", "b"))
    frames = _renderer(args).render(coeffs)
    tmp = args.out.with_name(args.out.name + ".partial")
    with tmp.open("wb") as fh:  # written whole, then moved: a failed run leaves no half file
        np.save(fh, frames)
    tmp.replace(args.out)
    print(f"{args.out}: {frames.shape[0]} frames of {frames.shape[2]}x{frames.shape[1]} (float32)")
    return 0


def run_sheet(args: argparse.Namespace) -> int:
    from service.render.sheet import write_sheet

    _writable(args.out, ".png")
    write_sheet(_renderer(args), args.out, seed=args.seed)
    print(f"{args.out}: written")
    return 0
