"""``meniscope bench render``: our renderer against Blender Cycles on the same coefficient draws.

Both render the same N seeded draws from ``CoefficientRanges`` in one run, so their
speeds are measured under the same machine load. Ours at several settings (supersampling x
sun samples: the speed-for-accuracy trade), each timed over ``--repeats`` passes after a
warm-up call; Cycles per frame, excluding Blender's one-time start (reported too). Per
setting: median frames/s, the ratio to Cycles, the agreement of ``service.render.agreement``, and the defects' sun
glints (the fluid at rest, with the spheres minus without: their flux, ours over Cycles'). Writes ``render.json``, ``render.md``,
``render.png`` (ours | Cycles | difference for a few frames), both frame stacks (ours at the last setting) and the
coefficients to ``--out``, and prints the table.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from service.bench import parse_pairs
from service.bench.results import write_results
from service.errors import MeniscopeError
from service.physics import CoefficientRanges
from service.plotting import pyplot
from service.scene import Scene
from service.verbs import add_scene_option

if TYPE_CHECKING:
    from service.render import Renderer

#: (frames, samples) for a full run and for ``--quick``.
FULL, QUICK = (300, 32), (12, 8)
#: Our renderer's settings measured by default, "SUPERSAMPLExSUN_SAMPLES": fastest to most accurate.
SETTINGS = "1x1,2x1,2x4,4x16"


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("render", help="our renderer vs Blender Cycles: speed and agreement", description=__doc__)
    add_scene_option(p)
    p.add_argument("--frames", type=int, help=f"coefficient draws (default {FULL[0]}, --quick {QUICK[0]})")
    p.add_argument("--samples", type=int, help=f"Cycles samples per pixel (default {FULL[1]}, --quick {QUICK[1]})")
    p.add_argument("--quick", action="store_true", help="a short smoke run")
    p.add_argument("--seed", type=int, default=0, help="seed of the coefficient draws")
    p.add_argument(
        "--settings",
        default=SETTINGS,
        help=f"our renderer's settings, SUPERSAMPLExSUN_SAMPLES, comma-separated (default {SETTINGS})",
    )
    p.add_argument("--repeats", type=int, default=5, help="timed passes over the draws per setting (median reported)")
    p.add_argument("--blender", default="blender", help="Blender executable")
    p.add_argument("--out", type=Path, default=Path("bench-render"), help="folder for the results")
    p.set_defaults(func=run)


def parse_settings(text: str) -> list[tuple[int, int]]:
    """ "2x4,1x1" -> [(2, 4), (1, 1)]; a one-line error for anything else."""
    return parse_pairs(text, "--settings", "SUPERSAMPLExSUN_SAMPLES like 2x4")


def time_ours(
    render: Callable[[np.ndarray], np.ndarray], coeffs: np.ndarray, repeats: int, label: str
) -> tuple[np.ndarray, float, np.ndarray]:
    """Frames (N, H, W), the warm-up call's seconds, and seconds per frame of each timed pass (repeats,)."""
    start = time.perf_counter()
    render(coeffs[:1])
    warmup = time.perf_counter() - start
    per_frame = []
    for _ in tqdm(range(repeats), desc=f"ours {label}", unit="pass"):
        start = time.perf_counter()
        frames = render(coeffs)
        per_frame.append((time.perf_counter() - start) / len(coeffs))
    return frames, warmup, np.array(per_frame)


def _rate(seconds_per_frame: float) -> float | None:
    return 1.0 / seconds_per_frame if seconds_per_frame > 0 else None


def _fmt(x: float | None, spec: str = ".3g") -> str:
    return "n/a" if x is None else format(x, spec)


def glint_fluxes(render: Callable[[Scene, np.ndarray], np.ndarray], scene: Scene) -> np.ndarray:
    """Each defect's sun glint (G,) in ``render(scene, coeffs)``'s frames: the fluid at rest with the spheres minus
    without them, summed over the detector's square round where it glints (its flux, full-scale pixels; 0 outside the
    frame); empty where the scene has no sphere."""
    from service.calibration.artifacts import glint_positions, square_flux, with_spheres

    if not len(scene.spheres):
        return np.zeros(0)
    rest = np.zeros((1, 4))
    glints = render(scene, rest)[0].astype(np.float64) - render(with_spheres(scene, np.zeros((0, 4))), rest)[0]
    return square_flux(glints, glint_positions(scene, scene.spheres))


def _through(renderer: Renderer, **rays: int) -> Callable[[Scene, np.ndarray], np.ndarray]:
    """:func:`glint_fluxes`' ``render``: ``renderer``'s own scene through it (built once: the large ones take
    seconds), any other (the scene without its spheres) through a new renderer of the same ``rays``."""
    from service.render import Renderer

    return lambda s, c: (renderer if s is renderer.scene else Renderer(s, **rays)).render(c)


def flux_ratios(ours: np.ndarray, cycles: np.ndarray, gain: float | None) -> dict[str, float | int | None]:
    """Ours over Cycles' glint flux (gain applied) of the defects Cycles shows (over 1e-3 of a full-scale pixel):
    median, lowest and highest, and how many."""
    shown = np.isfinite(ours) & np.isfinite(cycles) & (cycles > 1e-3)
    ratio = (gain or 1.0) * ours[shown] / cycles[shown]
    if not ratio.size:
        return {"defects": 0, "flux_ratio_median": None, "flux_ratio_min": None, "flux_ratio_max": None}
    return {
        "defects": int(ratio.size),
        "flux_ratio_median": float(np.median(ratio)),
        "flux_ratio_min": float(ratio.min()),
        "flux_ratio_max": float(ratio.max()),
    }


def markdown(results: dict) -> str:
    """The results as Markdown: one row per setting of ours beside Cycles, speed ratio and agreement."""
    c = results["cycles"]
    n = results["frames"]
    lines = [
        f"Renderer benchmark: {n} draws, scene {results['scene']['path']}, "
        f"load average {results['host']['load_before']:.2f} -> {results['host']['load_after']:.2f} "
        f"on {results['host']['cpus']} CPUs. Blender Cycles, {c['samples']} spp: "
        f"{_fmt(c['frames_per_s'])} frames/s (median {_fmt(c['median_s_per_frame'])} s/frame; "
        f"one-time start {_fmt(c['startup_s'])} s).",
        "",
        "| ours (supersample x sun samples) | frames/s (median) | x Cycles | first call (s) | "
        "correlation median / p10 | centroid median / p90 (px) | highlight in both | gain | "
        "defects' glint flux, ours / Cycles: median (range) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for o in results["ours"]:
        a, d = o["agreement"], o["glints"]
        lines.append(
            f"| {o['supersample']} x {o['sun_samples']} | {_fmt(o['frames_per_s'], '.0f')} | "
            f"{_fmt(o['speed_ratio'], '.0f')} | {_fmt(o['warmup_s'])} | "
            f"{_fmt(a['correlation_median'], '.4f')} / {_fmt(a['correlation_p10'], '.4f')} | "
            f"{_fmt(a['centroid_distance_median_px'])} / {_fmt(a['centroid_distance_p90_px'])} | "
            f"{a['highlight_both']}/{n} | {_fmt(a['gain_median'])} | "
            f"{_fmt(d['flux_ratio_median'])} ({_fmt(d['flux_ratio_min'])}-{_fmt(d['flux_ratio_max'])}) of {d['defects']} |"
        )
    return "\n".join(lines) + "\n"


def figure(ours: np.ndarray, cycles: np.ndarray, agreement, path: Path, label: str = "ours", rows: int = 4) -> None:
    """PNG of ``rows`` frames, ours | Cycles | Cycles - ours: best, middle and worst centroid distances."""
    plt = pyplot()

    both = np.flatnonzero(agreement.both_found)
    pool = both[np.argsort(agreement.distance_px[both])] if both.size else np.arange(len(ours))
    picks = pool[np.unique(np.linspace(0, len(pool) - 1, min(rows, len(pool))).round().astype(int))]
    fig, axes = plt.subplots(len(picks), 3, figsize=(9, 3 * len(picks)), squeeze=False)
    for row, i in zip(axes, picks):
        diff = cycles[i] - ours[i]
        lim = max(float(np.abs(diff).max()), 1e-6)
        row[0].imshow(ours[i], cmap="gray", vmin=0, vmax=1)
        row[1].imshow(cycles[i], cmap="gray", vmin=0, vmax=1)
        im = row[2].imshow(diff, cmap="coolwarm", vmin=-lim, vmax=lim)
        fig.colorbar(im, ax=row[2], fraction=0.046)
        dist = f"{agreement.distance_px[i]:.2f} px" if agreement.both_found[i] else "no highlight in both"
        row[0].set_title(f"{label}, frame {i}")
        row[1].set_title(f"Cycles ({dist})")
        row[2].set_title(f"Cycles - ours (r = {agreement.correlation[i]:.3f})")
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    from service.render import Renderer
    from service.render.agreement import compare
    from service.render.blender import BlenderRenderer

    default_frames, default_samples = QUICK if args.quick else FULL
    frames = default_frames if args.frames is None else args.frames
    samples = default_samples if args.samples is None else args.samples
    for name, value in (("--frames", frames), ("--samples", samples), ("--repeats", args.repeats)):
        if value < 1:
            raise MeniscopeError(name, f"must be at least 1, got {value}")
    settings = parse_settings(args.settings)
    scene = Scene.load(args.scene)
    coeffs = CoefficientRanges().sample(frames, np.random.default_rng(args.seed))  # (N, 4): d, p, a, b
    load_before = os.getloadavg()[0]

    blender = BlenderRenderer(scene, samples=samples, blender=args.blender, seed=args.seed)
    cycles = blender.render(coeffs)
    timing = blender.last_timing
    cycles_glints = glint_fluxes(
        lambda s, c: BlenderRenderer(s, samples=samples, blender=args.blender, seed=args.seed).render(c), scene
    )
    cycles_median = float(np.median(timing.frame_s))
    cycles_rate = _rate(cycles_median)
    ours_results, best = [], None
    for ss, sun in settings:
        renderer = Renderer(scene, supersample=ss, sun_samples=sun)
        ours, warmup, ours_s = time_ours(renderer.render, coeffs, args.repeats, f"{ss}x{sun}")
        agreement = compare(ours, cycles)
        summary = agreement.summary()
        rate = _rate(float(np.median(ours_s)))
        ours_results.append(
            {
                "supersample": ss,
                "sun_samples": sun,
                "warmup_s": warmup,
                "median_s_per_frame": float(np.median(ours_s)),
                "frames_per_s": rate,
                "speed_ratio": rate / cycles_rate if rate and cycles_rate else None,
                "agreement": summary,
                "glints": flux_ratios(
                    glint_fluxes(_through(renderer, supersample=ss, sun_samples=sun), scene),
                    cycles_glints,
                    summary["gain_median"],
                ),
            }
        )
        best = (ours, agreement, ss, sun)  # the last (most accurate) setting goes into the figure
    results = {
        "schema": "meniscope.bench.render/3",
        "scene": {"path": str(args.scene), "sha256": scene.sha256},
        "seed": args.seed,
        "frames": frames,
        "host": {"cpus": os.cpu_count(), "load_before": load_before, "load_after": os.getloadavg()[0]},
        "cycles": {
            "samples": samples,
            "startup_s": timing.startup_s,
            "median_s_per_frame": cycles_median,
            "frames_per_s": cycles_rate,
        },
        "ours": ours_results,
    }
    table = markdown(results)
    write_results(args.out / "render.json", results, table)
    ours, agreement, ss, sun = best
    np.save(args.out / "ours.npy", ours)
    np.save(args.out / "cycles.npy", cycles)
    np.savetxt(args.out / "coefficients.csv", coeffs, delimiter=",", header="d,p,a,b", comments="")
    figure(ours, cycles, agreement, args.out / "render.png", label=f"ours {ss}x{sun}")
    return 0
