"""``meniscope bench analysis``: every inverse method through the whole analysis, on the same simulated
recordings, scored against their truth (the accuracy figures of the analysis issue) and timed.

Per method and noise level: frames/s end to end from the file (inversion, segmentation, fits;
the method's one-time setup, such as indexing a database, apart), segmentation precision and
recall (+-2 frames), median and 90th-percentile relative errors of the dominant frequency, decay
rate and amplitude, offset error (mm), the share of windows whose intervals hold the truth, per-frame RMSE of D(0, t) and of the coefficients, D(0, t)
correlation, and the peak memory of the process that ran the method. Recordings are every ``*.cine``/``*.avi`` with a ``.truth.json`` in ``--recordings``.
"""

from __future__ import annotations

import argparse
import multiprocessing
import resource
import time
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from service import DEFAULT_MODELS
from service.analysis.offline import analyse_recording, method_label
from service.analysis.results import FitSettings
from service.bench.results import write_results
from service.errors import MeniscopeError, require_folder_of
from service.inverse.methods import DATABASE_METHODS, METHODS, database_folder, open_method
from service.scene import Scene
from service.simulate import truth_path
from service.validation.score import QUANTITIES, error_statistics, settling_statistics, summary
from service.validation.truth import read_truth
from service.verbs import add_scene_option

#: Summary figures of a method's recordings (:func:`aggregate`), as (key, label, format) of the table.
COLUMNS = (
    ("frames_per_s", "frames/s", ".0f"),
    ("precision", "seg. precision", ".3f"),
    ("recall", "seg. recall", ".3f"),
    ("frequency_median", "freq. err. median", ".2%"),
    ("frequency_p90", "p90", ".2%"),
    ("decay_median", "decay err. median", ".1%"),
    ("decay_p90", "p90", ".1%"),
    ("amplitude_median", "ampl. err. median", ".1%"),
    ("amplitude_p90", "p90", ".1%"),
    ("offset_mm_median", "offset err. median (um)", "um"),
    ("offset_mm_p90", "p90", "um"),
    ("frequency_coverage", "freq. CI coverage", ".0%"),
    ("decay_coverage", "decay CI cov.", ".0%"),
    ("amplitude_coverage", "ampl. CI cov.", ".0%"),
    ("offset_mm_coverage", "offset CI cov.", ".0%"),
    ("settled_right", "settled verdict right", ".0%"),
    ("settled_falsely", "unsettled called settled", ".0%"),
    ("centre_rmse_mm", "D(0,t) RMSE (um)", "um"),
    ("centre_correlation", "D(0,t) corr.", ".3f"),
    ("a_mm_rmse", "a RMSE (um)", "um"),
    ("b_mm_rmse", "b RMSE (um)", "um"),
    ("p_rmse", "p RMSE", ".3f"),
    ("peak_memory_mb", "peak MB", ".0f"),
)


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "analysis", help="each inverse method through the analysis, scored on simulated recordings", description=__doc__
    )
    p.add_argument("--recordings", type=Path, required=True, help="folder of simulated recordings with truth")
    add_scene_option(p)
    p.add_argument("--methods", default="network,direct", help=f"comma-separated, of {', '.join(METHODS)}")
    p.add_argument("--models", type=Path, default=DEFAULT_MODELS, help="model folder (default: the shipped one)")
    p.add_argument("--database", type=Path, help="render database of the nearest-neighbour methods")
    p.add_argument(
        "--refine",
        action="store_true",
        help="each window's motion refined on its frames through the renderer (analyze --refine)",
    )
    p.add_argument(
        "--series",
        help="comma-separated, of steady, window: the series each window is fitted to (analyze --series; default "
        "both), with --refine the one whose fit the refinement starts from (default window: what analyze --refine "
        "does); window rows are the network method's only",
    )
    p.add_argument("--out", type=Path, default=Path("bench-analysis.json"), help="JSON of the results (+ .md)")
    p.add_argument(
        "--reports",
        type=Path,
        help="folder to keep each recording's REPORT.json in (as analyze writes it), one subfolder per row's method, "
        "to look at the windows behind the figures",
    )
    p.set_defaults(func=run)


def recordings_in(folder: Path) -> list[Path]:
    """Simulated recordings in ``folder``: those with a truth sidecar, sorted by name."""
    found = sorted(p for p in folder.glob("*") if p.suffix.lower() in (".cine", ".avi") and truth_path(p).exists())
    if not found:
        raise MeniscopeError(folder, "no recordings with a .truth.json sidecar (make some with `meniscope simulate`)")
    return found


def run_method(
    method: str,
    recordings: list[Path],
    scene: Scene,
    models: Path,
    database: Path | None,
    refine: bool = False,
    series: str = "steady",
    reports: Path | None = None,
) -> dict:
    """Open ``method`` once (timed), then one row per recording: noise preset, wall time, frames and
    :func:`summary` figures; with this process's peak resident memory. Run in a fresh process per method.
    ``refine``: each window's motion refined on its frames (:mod:`service.inverse.synthesis`); ``series``:
    :attr:`FitSettings.series_model`; ``reports``: each recording's report kept there, in the row's
    :func:`row_label` folder."""
    settings = FitSettings(series_model=series)
    start = time.perf_counter()
    opened = open_method(method, scene, models, database)
    setup_s = time.perf_counter() - start
    rows = []
    for path in recordings:
        truth = read_truth(path)
        start = time.perf_counter()
        analysis = analyse_recording(
            path, scene, method, models, database, settings=settings, progress=False, opened=opened, refine=refine
        )
        seconds = time.perf_counter() - start
        if reports is not None:
            folder = reports / row_label(method, refine, series)
            folder.mkdir(parents=True, exist_ok=True)
            analysis.report.write(folder / f"{path.stem}.json")
        rows.append(
            {
                "recording": path.name,
                "noise": truth.get("noise"),
                "seconds": seconds,
                "frames": analysis.report.source.frames,
                "windows_fitted": len(analysis.report.windows),
                **summary(analysis.report, truth, analysis.per_frame),
            }
        )
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"setup_s": setup_s, "peak_memory_mb": peak_mb, "rows": rows}


def row_label(method: str, refine: bool, series: str) -> str:
    """The table's name of a method run: the report's method label, and "+window" where the window model's series
    is fitted; with ``refine``, "+steady" where the network method's refinement starts from the steady series' fit
    (``analyze --refine --series steady``) rather than the window model's (``analyze --refine``)."""
    if refine:
        return method_label(method, refine) + ("+steady" if method == "network" and series == "steady" else "")
    return method_label(method, refine) + ("+window" if series == "window" else "")


def run_method_apart(*args: object) -> dict:
    """:func:`run_method` of ``args`` in a fresh process, so that its peak memory is the method's own."""
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(run_method, *args).result()


def aggregate(rows: list[dict]) -> dict:
    """The errors' medians and 90th percentiles and the settled verdicts' shares over the set's windows pooled (what
    a user reads as the set's figures; a mean of each recording's own would weigh a 4-window recording as much as a
    40-window one and let one recording's bad tail set the p90), means over recordings of the other summary figures
    (None where no recording had it); frames/s overall."""
    out = {"recordings": len(rows), "frames_per_s": sum(r["frames"] for r in rows) / sum(r["seconds"] for r in rows)}
    for key, _, _ in COLUMNS[1:-1]:  # peak memory is the method's, not per recording
        values = [r[key] for r in rows if r.get(key) is not None]
        out[key] = float(np.mean(values)) if values else None
    pooled = {key: np.concatenate([np.asarray(r[f"{key}_errors"], np.float64) for r in rows]) for key in QUANTITIES}
    settled = [np.array([v for r in rows for v in r.get(f"settled_{k}", [])], np.int64) for k in ("true", "said")]
    return out | error_statistics(pooled) | settling_statistics(*settled)


def _cell(value: float | None, spec: str) -> str:
    if value is None:
        return "n/a"
    return f"{value * 1e3:.2f}" if spec == "um" else format(value, spec)


def markdown(results: dict) -> str:
    lines = [
        "| method | noise | " + " | ".join(label for _, label, _ in COLUMNS) + " |",
        "|---" * (len(COLUMNS) + 2) + "|",
    ]
    for method, by_noise in results["methods"].items():
        for noise, figures in by_noise.items():
            lines.append(f"| {method} | {noise} | " + " | ".join(_cell(figures[k], s) for k, _, s in COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise MeniscopeError("--methods", f"unknown {unknown}; choose from {', '.join(METHODS)}")
    if any(m in DATABASE_METHODS for m in methods):
        database_folder(args.models, args.database)  # refuses a missing database before any method runs
    require_folder_of(args.out)
    if args.reports is not None:
        require_folder_of(args.reports)
        if args.reports.exists() and not args.reports.is_dir():
            raise MeniscopeError(args.reports, "not a folder: --reports keeps one report per recording in it")
    recordings = recordings_in(args.recordings)
    scene = Scene.load(args.scene)
    results: dict = {"recordings": [p.name for p in recordings], "methods": {}, "per_recording": {}}
    asked = args.series or ("window" if args.refine else "steady,window")
    series = [s.strip() for s in asked.split(",") if s.strip()]
    if not series or any(s not in ("steady", "window") for s in series):
        raise MeniscopeError("--series", f"{asked!r}: choose from steady, window")
    runs = [(m, s) for m in methods for s in series if s == "steady" or m == "network"]
    if not runs:  # nothing to measure is a mistake in the options, not an empty table
        raise MeniscopeError("--series", f"{asked!r} gives no rows: window rows are the network method's")
    for method, fitted in runs:
        measured = run_method_apart(
            method, recordings, scene, args.models, args.database, args.refine, fitted, args.reports
        )
        method = row_label(method, args.refine, fitted)
        rows = measured["rows"]
        by_noise = defaultdict(list)
        for r in rows:
            by_noise[r["noise"] or "unknown"].append(r)
        results["per_recording"][method] = rows
        results["methods"][method] = {
            noise: {**aggregate(group), "setup_s": measured["setup_s"], "peak_memory_mb": measured["peak_memory_mb"]}
            for noise, group in sorted(by_noise.items())
        }
        print(
            f"{method}: done ({len(rows)} recordings, setup {measured['setup_s']:.1f} s, "
            f"peak {measured['peak_memory_mb']:.0f} MB)"
        )
    write_results(args.out, results, markdown(results))
    return 0
