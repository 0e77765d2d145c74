"""``meniscope bench analysis``: every inverse method through the whole analysis, on the same simulated
recordings, scored against their truth (the accuracy figures of the analysis issue) and timed.

Per method and noise level: frames/s end to end from the file (inversion, segmentation, fits),
segmentation precision and recall (+-2 frames), median and 90th-percentile relative errors of the
dominant frequency, decay rate and amplitude, offset error (mm), and per-frame D(0, t) RMSE and
correlation. Recordings are every ``*.cine``/``*.avi`` with a ``.truth.json`` in ``--recordings``.
"""
from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from service import DEFAULT_MODELS
from service.analysis.offline import analyse_recording
from service.analysis.score import load_truth, summary
from service.cli import add_scene_option
from service.errors import MeniscopeError, require_folder_of
from service.inverse.methods import DATABASE_METHODS, METHODS
from service.scene import Scene
from service.simulate import truth_path

#: Summary figures averaged over a method's recordings, as (key, label, format) of the table.
COLUMNS = (
    ("frames_per_s", "frames/s", ".0f"), ("precision", "seg. precision", ".3f"), ("recall", "seg. recall", ".3f"),
    ("frequency_median", "freq. err. median", ".2%"), ("frequency_p90", "p90", ".2%"),
    ("decay_median", "decay err. median", ".1%"), ("decay_p90", "p90", ".1%"),
    ("amplitude_median", "ampl. err. median", ".1%"), ("offset_mm_median", "offset err. median (um)", "um"),
    ("centre_rmse_mm", "D(0,t) RMSE (um)", "um"), ("centre_correlation", "D(0,t) corr.", ".3f"),
)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("analysis", help="each inverse method through the analysis, scored on simulated recordings",
                              description=__doc__)
    p.add_argument("--recordings", type=Path, required=True, help="folder of simulated recordings with truth")
    add_scene_option(p)
    p.add_argument("--methods", default="network,direct", help=f"comma-separated, of {', '.join(METHODS)}")
    p.add_argument("--models", type=Path, default=DEFAULT_MODELS, help="model folder (default: the shipped one)")
    p.add_argument("--database", type=Path, help="render database of the nearest-neighbour methods")
    p.add_argument("--out", type=Path, default=Path("bench-analysis.json"), help="JSON of the results (+ .md)")
    p.set_defaults(func=run)


def recordings_in(folder: Path) -> list[Path]:
    """Simulated recordings in ``folder``: those with a truth sidecar, sorted by name."""
    found = sorted(p for p in folder.glob("*") if p.suffix.lower() in (".cine", ".avi") and truth_path(p).exists())
    if not found:
        raise MeniscopeError(folder, "no recordings with a .truth.json sidecar (make some with `meniscope simulate`)")
    return found


def run_method(method: str, recordings: list[Path], scene: Scene, models: Path, database: Path | None) -> list[dict]:
    """One row per recording: its noise preset, wall time, frames and :func:`summary` figures."""
    rows = []
    for path in recordings:
        truth = load_truth(truth_path(path))
        start = time.perf_counter()
        analysis = analyse_recording(path, scene, method, models, database, progress=False)
        seconds = time.perf_counter() - start
        rows.append({"recording": path.name, "noise": truth.get("noise"), "seconds": seconds,
                     "frames": analysis.report.source.frames,
                     **summary(analysis.report, truth, analysis.per_frame.centre)})
    return rows


def aggregate(rows: list[dict]) -> dict:
    """Means over recordings of each summary figure (None where no recording had it); frames/s overall."""
    out = {"recordings": len(rows), "frames_per_s": sum(r["frames"] for r in rows) / sum(r["seconds"] for r in rows)}
    for key, _, _ in COLUMNS[1:]:
        values = [r[key] for r in rows if r.get(key) is not None]
        out[key] = float(np.mean(values)) if values else None
    return out


def _cell(value: float | None, spec: str) -> str:
    if value is None:
        return "n/a"
    return f"{value * 1e3:.2f}" if spec == "um" else format(value, spec)


def markdown(results: dict) -> str:
    lines = ["| method | noise | " + " | ".join(label for _, label, _ in COLUMNS) + " |",
             "|---" * (len(COLUMNS) + 2) + "|"]
    for method, by_noise in results["methods"].items():
        for noise, figures in by_noise.items():
            lines.append(f"| {method} | {noise} | " + " | ".join(_cell(figures[k], s) for k, _, s in COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise MeniscopeError("--methods", f"unknown {unknown}; choose from {', '.join(METHODS)}")
    if any(m in DATABASE_METHODS for m in methods) and args.database is None and not (args.models / "database").is_dir():
        raise MeniscopeError("--database", "the nearest-neighbour methods need a render database")
    require_folder_of(args.out)
    recordings = recordings_in(args.recordings)
    scene = Scene.load(args.scene)
    results: dict = {"recordings": [p.name for p in recordings], "methods": {}, "per_recording": {}}
    for method in methods:
        rows = run_method(method, recordings, scene, args.models, args.database)
        by_noise = defaultdict(list)
        for r in rows:
            by_noise[r["noise"] or "unknown"].append(r)
        results["per_recording"][method] = rows
        results["methods"][method] = {noise: aggregate(group) for noise, group in sorted(by_noise.items())}
        print(f"{method}: done ({len(rows)} recordings)")
    args.out.write_text(json.dumps(results, indent=2, allow_nan=False) + "\n")
    table = markdown(results)
    args.out.with_suffix(".md").write_text(table)
    print(table)
    return 0
