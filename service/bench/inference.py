"""``meniscope bench inference``: the learned methods' graphs alone, under each onnxruntime setting worth a
choice, so that the service's defaults are the fastest measured.

For each model folder and learned method, and each combination of intra-op threads, batch size and
graph optimisation level: the same ROI frames of one recording are run through
:class:`service.inverse.network.NetworkMethod` (exactly what ``analyze`` and ``serve`` call) several
times, in turns; the median pass gives frames/s. The first pass after opening is a warm-up and not counted.
Writes JSON and a Markdown table (``--out``, ``.md`` beside it).
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path

import numpy as np

from service import DEFAULT_MODELS
from service.bench.results import write_results
from service.errors import MeniscopeError, require_folder_of
from service.inverse.manifest import load_manifest
from service.inverse.network import OPTIMISATION, NetworkMethod
from service.pipeline.demo import DEMO_AVI
from service.recordings.roi import read_roi_frames
from service.scene import Scene
from service.verbs import add_scene_option


def _choices(option: str, text: str, allowed: set[str] | None = None) -> list:
    """A comma-separated option's values: positive whole numbers, or names among ``allowed``; one-line errors."""
    values = [v.strip() for v in text.split(",") if v.strip()]
    if allowed is not None:
        if values and set(values) <= allowed:
            return values
        raise MeniscopeError(option, f"choose among {', '.join(sorted(allowed))}, got {text!r}")
    if values and all(v.isdigit() and int(v) > 0 for v in values):
        return [int(v) for v in values]
    raise MeniscopeError(option, f"expected positive whole numbers separated by commas, got {text!r}")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "inference", help="the learned methods' graphs alone: threads, batch, optimisation", description=__doc__
    )
    add_scene_option(p)
    p.add_argument(
        "--models", type=Path, action="append", help="model folder; repeat for more (default: the shipped one)"
    )
    p.add_argument("--recording", type=Path, default=DEMO_AVI, help="whose ROI frames are inferred (default: the demo)")
    p.add_argument("--frames", type=int, default=2048, help="frames per pass, at most the recording's (default 2048)")
    p.add_argument("--repeats", type=int, default=7, help="timed passes per setting; the median counts (default 7)")
    p.add_argument("--threads", default="1,2", help="intra-op thread counts (default 1,2)")
    p.add_argument("--batches", default="16,64,256,1024", help="batch sizes (default 16,64,256,1024)")
    p.add_argument(
        "--optimisation",
        default="basic,all",
        help=f"graph optimisation levels, of {', '.join(OPTIMISATION)} (default basic,all)",
    )
    p.add_argument("--out", type=Path, default=Path("bench-inference.json"), help="JSON of the results (+ .md)")
    p.set_defaults(func=run)


def _pass(method: NetworkMethod, frames: np.ndarray) -> float:
    """Seconds of one pass of ``method`` over ``frames``."""
    start = time.perf_counter()
    method.infer(frames)
    return time.perf_counter() - start


def measure(
    models: list[Path],
    scene: Scene,
    frames: np.ndarray,
    threads: list[int],
    batches: list[int],
    levels: list[str],
    repeats: int,
) -> list[dict]:
    """One row per model folder, method and setting: its label, the setting and median frames/s.

    Every setting is opened and warmed first, then timed in turns (one pass each per round), so
    that a busy spell of the machine falls on all of them alike rather than on a few.
    """
    rows, methods = [], []
    for folder in models:
        manifest = load_manifest(folder, scene)
        for name, n, batch, level in itertools.product(manifest.methods, threads, batches, levels):
            methods.append(NetworkMethod(folder, scene, name, threads=n, batch=batch, optimisation=level))
            rows.append(
                {
                    "label": manifest.label(name),
                    "models": str(folder),
                    "threads": n,
                    "batch": batch,
                    "optimisation": level,
                }
            )
            _pass(methods[-1], frames)
    seconds = np.array([[_pass(m, frames) for m in methods] for _ in range(repeats)])  # (repeats, settings)
    for row, median in zip(rows, np.median(seconds, axis=0)):
        row["frames_per_s"] = len(frames) / float(median)
    return rows


def markdown(rows: list[dict]) -> str:
    """Frames/s, one row per method and setting, with each method's fastest setting marked."""
    best = {}
    for r in rows:
        best[r["label"]] = max(best.get(r["label"], 0.0), r["frames_per_s"])
    lines = [
        "| method | threads | batch | optimisation | frames/s (median) | of its fastest |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        share = r["frames_per_s"] / best[r["label"]]
        lines.append(
            f"| {r['label']} | {r['threads']} | {r['batch']} | {r['optimisation']} | {r['frames_per_s']:.0f} | "
            f"{share:.0%}{' (fastest)' if share == 1 else ''} |"
        )
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    for option, value in (("--frames", args.frames), ("--repeats", args.repeats)):
        if value < 1:
            raise MeniscopeError(option, f"must be at least 1, got {value}")
    threads, batches = _choices("--threads", args.threads), _choices("--batches", args.batches)
    levels = _choices("--optimisation", args.optimisation, set(OPTIMISATION))
    require_folder_of(args.out)
    scene = Scene.load(args.scene)
    frames, _ = read_roi_frames(args.recording, scene, args.frames)
    rows = measure(args.models or [DEFAULT_MODELS], scene, frames, threads, batches, levels, args.repeats)
    results = {"recording": str(args.recording), "frames": len(frames), "repeats": args.repeats, "rows": rows}
    write_results(args.out, results, markdown(rows))
    return 0
