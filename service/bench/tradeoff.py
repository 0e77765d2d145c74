"""``meniscope bench tradeoff``: every inverse method on the same held-out recordings in one run, with the
renderer, the window fit and the live pipeline measured beside them, so a user can choose with numbers.

Steps, all in this one run: simulate held-out recordings at two noise levels (or reuse those in
``--out``), beside any folders of recordings given (``--recordings``: Blender Cycles ones, say); every inverse
method through the whole analysis on each set (``bench analysis``: frames/s from the file, ms per window,
dominant frequency / decay / amplitude errors and the offset's, median and p90, per-frame RMSE, peak memory; one
fresh process per method): the network with its window model (what ``analyze`` runs by default) and with its
steady series, the other learned methods, the nearest-neighbour ones, and the window inversion by synthesis
(``analyze --refine``, on each set's first recordings only: seconds a window); our window fit against harminv
on the same series (``bench fit``); our renderer against Blender Cycles (``bench render``); the replay
pipeline's real-time factor (``bench serve``: frames inferred per second over the recording's rate). Writes
``tradeoff.json``, ``tradeoff.md`` (each method's row says which target it misses) and ``tradeoff.png``
(speed against accuracy, one point per method and recording set).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from service import DEFAULT_MODELS
from service.bench import analysis, fit
from service.bench.results import write_results
from service.errors import MeniscopeError
from service.inverse import window_model
from service.inverse.manifest import load_manifest
from service.plotting import pyplot
from service.scene import Scene
from service.verbs import add_scene_option

#: (windows per recording, seeds, fit-suite windows per category, render frames flag, serve seconds, recordings of
#: each set the refinement by synthesis runs on) of the two modes.
MODES = {"quick": (1, (201,), 1, ["--quick"], 3.0, 1), "full": (12, (201, 202, 203), 25, [], 20.0, 1)}
NOISES = ("low", "high")
#: Issue 4's accuracy targets (relative, and the offset in mm) and the speed targets of issues 5, 3 and 17 (a
#: window's inversion within the window's 10 ms at 100 ejections/s).
TARGETS = {"frequency_median": 0.005, "decay_median": 0.05, "amplitude_median": 0.10, "offset_mm_median": 0.002}
CAMERA_FPS, REGULARISED_S_PER_WINDOW, WINDOW_MS = 19000.0, 1.0, 10.0


@dataclass(frozen=True)
class Row:
    """One method as the table measures it: its label, the per-frame method and model folder, the database of the
    nearest-neighbour ones, the series each window is fitted to (``FitSettings.series_model``) and whether its
    windows are refined by synthesis."""

    label: str
    method: str
    models: Path
    database: Path | None = None
    series: str = "steady"
    refine: bool = False


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "tradeoff", help="every inverse method side by side: speed against accuracy", description=__doc__
    )
    add_scene_option(p)
    p.add_argument("--mode", choices=list(MODES), default="full", help="quick: a smoke run of minutes (default full)")
    p.add_argument("--models", type=Path, default=DEFAULT_MODELS, help="model folder (default: the shipped one)")
    p.add_argument(
        "--more-models",
        type=Path,
        action="append",
        default=[],
        help="another model folder (another input size, an int8 copy from `meniscope quantize`) whose "
        "learned methods are measured as rows of their own; repeat for more",
    )
    p.add_argument(
        "--database",
        type=Path,
        action="append",
        default=[],
        help="render database(s) for the nearest-neighbour methods (`meniscope database`); repeat for "
        "20k and 100k; none: those methods are left out, and the table says so",
    )
    p.add_argument(
        "--recordings",
        action="append",
        default=[],
        metavar="LABEL=FOLDER",
        help="another set of recordings with their .truth.json (Blender Cycles ones, say: `meniscope simulate "
        "--renderer blender`), measured beside the simulated low and high noise sets under LABEL; repeat for more",
    )
    p.add_argument("--out", type=Path, default=Path("bench-tradeoff"), help="folder for recordings and results")
    p.set_defaults(func=run)


def _meniscope(*args: str | Path) -> None:
    """Run a meniscope verb as its own process (its timings are not disturbed by ours); errors stop the run.
    (-P: the working folder is not put on the import path, where a stray `service` folder would shadow us.)"""
    done = subprocess.run([sys.executable, "-P", "-m", "service.cli", *map(str, args)], capture_output=True, text=True)
    if done.returncode != 0:
        raise MeniscopeError(f"meniscope {args[0]}", (done.stderr.strip().splitlines() or ["failed"])[-1])


def given_sets(specs: list[str]) -> dict[str, Path]:
    """``--recordings LABEL=FOLDER`` as {label: folder}; each folder must hold recordings with their truth."""
    sets = {}
    for spec in specs:
        label, sep, folder = spec.partition("=")
        if not sep or not label or not folder:
            raise MeniscopeError("--recordings", f"{spec!r}: give LABEL=FOLDER")
        if label in NOISES or label in sets:
            raise MeniscopeError("--recordings", f"{spec!r}: the label {label!r} is taken")
        analysis.recordings_in(Path(folder))  # refuses a folder without recordings and their truth
        sets[label] = Path(folder)
    return sets


def recordings(out: Path, scene: Path, windows: int, seeds: tuple[int, ...]) -> dict[str, Path]:
    """Held-out recordings per noise level (a folder each), simulated by our renderer unless already there."""
    folders = {}
    for noise in NOISES:
        folder = out / "recordings" / noise
        folder.mkdir(parents=True, exist_ok=True)
        for seed in seeds:
            rec = folder / f"seed{seed}.cine"
            if not rec.exists():
                _meniscope(
                    "simulate", "--scene", scene, "--out", rec, "--windows", windows, "--seed", seed, "--noise", noise
                )
        folders[noise] = folder
    return folders


def methods(models: list[Path], databases: list[Path], scene: Scene) -> list[Row]:
    """Every method measured: the learned ones of each model folder (the network also with its window model, where
    the folder has one), per database the nearest ones, then the regularised one and the refinement by synthesis
    from the first folder's window model (or its network's steady series)."""
    rows = []
    for folder in models:
        manifest = load_manifest(folder, scene)
        for m in manifest.methods:
            if m == "network" and (folder / window_model.FILE).is_file():
                rows.append(Row(f"{manifest.label(m)} + window model", m, folder, series="window"))
            rows.append(Row(manifest.label(m), m, folder))
    for db in databases:
        rows += [Row(f"{m} {db.name}", m, models[0], db) for m in ("nearest", "nearest-approx")]
    if databases:
        rows.append(Row(f"regularised {databases[0].name}", "regularised", models[0], databases[0]))
    first = load_manifest(models[0], scene)
    series = "window" if (models[0] / window_model.FILE).is_file() else "steady"
    rows.append(Row(f"{first.label('network')} + synthesis", "network", models[0], series=series, refine=True))
    return rows


def misses(row: dict) -> list[str]:
    """The targets a method's row misses, in words."""
    out = [
        f"{k.split('_')[0]} "
        + ("not measured (no window with a mode)" if row.get(k) is None else f"{row[k]:.3g} > {v:g}")
        for k, v in TARGETS.items()
        if row.get(k) is None or row[k] > v
    ]
    if row.get("refine"):
        if row["ms_per_window"] > WINDOW_MS:
            out.append(f"{row['ms_per_window']:,.0f} ms/window > a window's {WINDOW_MS:g} ms")
    elif row["method"] in ("network", "direct") and row["frames_per_s"] < CAMERA_FPS:
        out.append(f"{row['frames_per_s']:,.1f} frames/s < camera {CAMERA_FPS:,.0f}")  # 18,999.6 is not 19000
    if row["method"] == "regularised" and row["ms_per_window"] > 1e3 * REGULARISED_S_PER_WINDOW:
        out.append(f"{row['ms_per_window'] / 1e3:.2f} s/window > 1 s")
    return out


def method_rows(spec: Row, folders: dict[str, Path], scene: Scene, refined: int) -> list[dict]:
    """One row per set of recordings for one method, measured in a fresh process (its own peak memory); a
    refinement by synthesis on the first ``refined`` recordings of each set."""
    rows = []
    for noise, folder in folders.items():
        found = analysis.recordings_in(folder)
        found = found[:refined] if spec.refine else found
        measured = analysis.run_method_apart(
            spec.method, found, scene, spec.models, spec.database, spec.refine, spec.series
        )
        figures = analysis.aggregate(measured["rows"])
        windows = sum(r["windows_fitted"] for r in measured["rows"])
        seconds = sum(r["seconds"] for r in measured["rows"])
        row = {
            "label": spec.label,
            "method": spec.method,
            "series": spec.series,
            "refine": spec.refine,
            "noise": noise,
            "recording_files": [r["recording"] for r in measured["rows"]],
            **figures,
            "ms_per_window": 1e3 * seconds / windows,
            "setup_s": measured["setup_s"],
            "peak_memory_mb": measured["peak_memory_mb"],
        }
        rows.append({**row, "misses": misses(row)})
        print(f"bench tradeoff: {spec.label}, {noise}: {row['frames_per_s']:.0f} frames/s", flush=True)
    return rows


def _pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:.2f} %"


def _um(v: float | None) -> str:
    return "n/a" if v is None else f"{1e3 * v:.2f}"


def markdown(results: dict) -> str:
    """The methods table, the recording sets, then the renderer, fit and pipeline figures measured beside them."""
    lines = [
        "| method | recordings | frames/s | ms/window | freq. err. median / p90 | decay err. median / p90 | "
        "ampl. err. median / p90 | offset err. median / p90 (um) | D(0,t) RMSE (um) | a RMSE (um) | peak MB | misses |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results["methods"]:
        lines.append(
            f"| {r['label']} | {r['noise']} | {r['frames_per_s']:.0f} | {r['ms_per_window']:.1f} | "
            f"{_pct(r['frequency_median'])} / {_pct(r['frequency_p90'])} | "
            f"{_pct(r['decay_median'])} / {_pct(r['decay_p90'])} | "
            f"{_pct(r['amplitude_median'])} / {_pct(r['amplitude_p90'])} | "
            f"{_um(r['offset_mm_median'])} / {_um(r['offset_mm_p90'])} | {_um(r['centre_rmse_mm'])} | "
            f"{_um(r['a_mm_rmse'])} | {r['peak_memory_mb']:.0f} | {'; '.join(r['misses']) or 'none'} |"
        )
    lines.append("\nRecording sets: " + "; ".join(f"{label}: {where}" for label, where in results["sets"].items()))
    lines.append(
        "The refinement by synthesis (+ synthesis) ran on each set's first "
        f"{results['refined_recordings']} recording(s) only: it costs seconds a window."
    )
    if not results["databases"]:
        lines.append("\nNo render database was given: the nearest-neighbour methods were left out.")
    lines += [
        "",
        "Beside them, in the same run:",
        "",
        fit.markdown(results["fit"]),
        Path(results["render_md"]).read_text(),
        "",
        f"Replay pipeline (`bench serve`, batch 512 x 1 thread, camera rate): real-time factor "
        f"{results['realtime_factor']:.3f} (frames inferred per second / the recording's frames per second).",
    ]
    return "\n".join(lines) + "\n"


#: The accuracy axes of the Pareto plot: (row key, scale to the plotted unit, axis label, target line or None).
PARETO_AXES = (
    ("frequency_median", 100, "dominant frequency error, median (%)", 100 * TARGETS["frequency_median"]),
    ("centre_rmse_mm", 1e3, "per-frame D(0, t) RMSE (um)", None),
)


def pareto(rows: list[dict], path: Path) -> None:
    """Frames/s (log) against the window-level accuracy (dominant frequency's median error) and the per-frame
    one (D(0, t) RMSE), one labelled point per method and noise level in each panel."""
    plt = pyplot()

    sets = list(dict.fromkeys(r["noise"] for r in rows))
    markers = dict(zip(sets, "os^vDP*X"))
    fig, axes = plt.subplots(1, len(PARETO_AXES), figsize=(15, 6), layout="constrained")
    for ax, (key, scale, label, target) in zip(axes, PARETO_AXES):
        for r in rows:
            if r[key] is None:
                continue
            ax.scatter(r["frames_per_s"], scale * r[key], marker=markers.get(r["noise"], "o"))
            ax.annotate(
                f"{r['label']} ({r['noise']})",
                (r["frames_per_s"], scale * r[key]),
                fontsize=6,
                xytext=(4, 2),
                textcoords="offset points",
            )
        ax.axvline(CAMERA_FPS, ls="--", color="0.5", lw=0.8)
        if target is not None:
            ax.axhline(target, ls="--", color="0.5", lw=0.8)
        ax.set(xscale="log", yscale="log", xlabel="frames/s, end to end from the file", ylabel=label)
    legend = ", ".join(f"{m} {name}" for name, m in markers.items())
    fig.suptitle(f"Speed against accuracy (dashed: camera rate and the 0.5 % frequency target); {legend}")
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    windows, seeds, fit_windows, render_flags, serve_s, refined = MODES[args.mode]
    for db in args.database:
        if not db.is_dir():
            raise MeniscopeError(db, "no render database there (make one with `meniscope database`)")
    given = given_sets(args.recordings)
    args.out.mkdir(parents=True, exist_ok=True)
    scene = Scene.load(args.scene)
    folders = {**recordings(args.out, args.scene, windows, seeds), **given}
    rows = [
        row
        for spec in methods([args.models, *args.more_models], args.database, scene)
        for row in method_rows(spec, folders, scene, refined)
    ]
    _meniscope("bench", "render", "--scene", args.scene, *render_flags, "--out", args.out / "render")
    rec = sorted(folders[NOISES[0]].glob("*.cine"))[0]
    _meniscope(
        "bench",
        "serve",
        "--source",
        rec,
        "--seconds",
        serve_s,
        "--configs",
        "512x1",
        "--speeds",
        "1",
        "--out",
        args.out / "serve",
    )
    serve = json.loads((args.out / "serve" / "serve.json").read_text())["runs"][0]
    results = {
        "mode": args.mode,
        "databases": [str(d) for d in args.database],
        "sets": {
            label: ("our renderer, " + label + " noise" if label in NOISES else "given") + f" ({folder})"
            for label, folder in folders.items()
        },
        "refined_recordings": refined,
        "methods": rows,
        "fit": fit.measure(fit_windows, 0, progress=False),
        "render": json.loads((args.out / "render" / "render.json").read_text()),
        "render_md": str(args.out / "render" / "render.md"),
        "serve": serve,
        "realtime_factor": serve["frames_per_s_inferred"] / CAMERA_FPS,
    }
    write_results(args.out / "tradeoff.json", results, markdown(results))
    pareto(rows, args.out / "tradeoff.png")
    return 0
