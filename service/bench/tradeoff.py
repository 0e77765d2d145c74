"""``meniscope bench tradeoff``: every inverse method on the same held-out recordings in one run, with the
renderer, the window fit and the live pipeline measured beside them, so a user can choose with numbers.

Steps, all in this one run: simulate held-out recordings at two noise levels (or reuse those in
``--out``); every inverse method through the whole analysis on them (``bench analysis``: frames/s
from the file, ms per window, dominant frequency / decay errors median and p90, per-frame RMSE,
peak memory; one fresh process per method); our window fit against harminv on the same series
(``bench fit``); our renderer against Blender Cycles (``bench render``); the replay pipeline's
real-time factor (``bench serve``: frames inferred per second over the recording's rate). Writes
``tradeoff.json``, ``tradeoff.md`` (each method's row says which target it misses) and
``tradeoff.png`` (speed against accuracy, one point per method and noise level).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from service import DEFAULT_MODELS
from service.bench import analysis, fit
from service.bench.results import write_results
from service.errors import MeniscopeError
from service.inverse.manifest import load_manifest
from service.plotting import pyplot
from service.scene import Scene
from service.verbs import add_scene_option

#: (windows per recording, seeds, fit-suite windows per category, render frames flag, serve seconds) of the two modes.
MODES = {"quick": (2, (201,), 1, ["--quick"], 3.0), "full": (12, (201, 202, 203), 25, [], 20.0)}
NOISES = ("low", "high")
#: Issue 4's accuracy targets (relative, and the offset in mm) and the speed targets of issues 5 and 3.
TARGETS = {"frequency_median": 0.005, "decay_median": 0.05, "amplitude_median": 0.10, "offset_mm_median": 0.002}
CAMERA_FPS, REGULARISED_S_PER_WINDOW = 19000.0, 1.0


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
    p.add_argument("--out", type=Path, default=Path("bench-tradeoff"), help="folder for recordings and results")
    p.set_defaults(func=run)


def _meniscope(*args: str | Path) -> None:
    """Run a meniscope verb as its own process (its timings are not disturbed by ours); errors stop the run.
    (-P: the working folder is not put on the import path, where a stray `service` folder would shadow us.)"""
    done = subprocess.run([sys.executable, "-P", "-m", "service.cli", *map(str, args)], capture_output=True, text=True)
    if done.returncode != 0:
        raise MeniscopeError(f"meniscope {args[0]}", (done.stderr.strip().splitlines() or ["failed"])[-1])


def recordings(out: Path, scene: Path, windows: int, seeds: tuple[int, ...]) -> dict[str, Path]:
    """Held-out recordings per noise level (a folder each), simulated unless already there."""
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


def methods(models: list[Path], databases: list[Path], scene: Scene) -> list[tuple[str, str, Path, Path | None]]:
    """(label, method, model folder, database) of every method measured: the learned ones of each model folder,
    then per database the nearest ones."""
    rows = []
    for folder in models:
        manifest = load_manifest(folder, scene)
        rows += [(manifest.label(m), m, folder, None) for m in manifest.methods]
    for db in databases:
        rows += [(f"{m} {db.name}", m, models[0], db) for m in ("nearest", "nearest-approx")]
    if databases:
        rows.append((f"regularised {databases[0].name}", "regularised", models[0], databases[0]))
    return rows


def misses(row: dict) -> list[str]:
    """The targets a method's row misses, in words."""
    out = [
        f"{k.split('_')[0]} "
        + ("not measured (no window with a mode)" if row.get(k) is None else f"{row[k]:.3g} > {v:g}")
        for k, v in TARGETS.items()
        if row.get(k) is None or row[k] > v
    ]
    if row["method"] in ("network", "direct") and row["frames_per_s"] < CAMERA_FPS:
        out.append(f"{row['frames_per_s']:,.1f} frames/s < camera {CAMERA_FPS:,.0f}")  # 18,999.6 is not 19000
    if row["method"] == "regularised" and row["ms_per_window"] > 1e3 * REGULARISED_S_PER_WINDOW:
        out.append(f"{row['ms_per_window'] / 1e3:.2f} s/window > 1 s")
    return out


def method_rows(
    label: str, method: str, db: Path | None, folders: dict[str, Path], scene: Scene, models: Path
) -> list[dict]:
    """One row per noise level for one method, measured in a fresh process (its own peak memory)."""
    rows = []
    for noise, folder in folders.items():
        measured = analysis.run_method_apart(method, analysis.recordings_in(folder), scene, models, db)
        figures = analysis.aggregate(measured["rows"])
        windows = sum(r["windows_fitted"] for r in measured["rows"])
        seconds = sum(r["seconds"] for r in measured["rows"])
        row = {
            "label": label,
            "method": method,
            "noise": noise,
            **figures,
            "ms_per_window": 1e3 * seconds / windows,
            "setup_s": measured["setup_s"],
            "peak_memory_mb": measured["peak_memory_mb"],
        }
        rows.append({**row, "misses": misses(row)})
        print(f"bench tradeoff: {label}, {noise} noise: {row['frames_per_s']:.0f} frames/s", flush=True)
    return rows


def _pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:.2f} %"


def markdown(results: dict) -> str:
    """The methods table, then the renderer, fit and pipeline figures measured beside them."""
    lines = [
        "| method | noise | frames/s | ms/window | freq. err. median / p90 | decay err. median / p90 | "
        "D(0,t) RMSE (um) | a RMSE (um) | peak MB | misses |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results["methods"]:
        lines.append(
            f"| {r['label']} | {r['noise']} | {r['frames_per_s']:.0f} | {r['ms_per_window']:.1f} | "
            f"{_pct(r['frequency_median'])} / {_pct(r['frequency_p90'])} | "
            f"{_pct(r['decay_median'])} / {_pct(r['decay_p90'])} | {1e3 * r['centre_rmse_mm']:.1f} | "
            f"{1e3 * r['a_mm_rmse']:.1f} | {r['peak_memory_mb']:.0f} | {'; '.join(r['misses']) or 'none'} |"
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

    fig, axes = plt.subplots(1, len(PARETO_AXES), figsize=(15, 6), layout="constrained")
    for ax, (key, scale, label, target) in zip(axes, PARETO_AXES):
        for r in rows:
            if r[key] is None:
                continue
            marker = "o" if r["noise"] == NOISES[0] else "s"
            ax.scatter(r["frames_per_s"], scale * r[key], marker=marker)
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
    fig.suptitle("Speed against accuracy (dashed: camera rate and the 0.5 % frequency target); o low, s high noise")
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    windows, seeds, fit_windows, render_flags, serve_s = MODES[args.mode]
    for db in args.database:
        if not db.is_dir():
            raise MeniscopeError(db, "no render database there (make one with `meniscope database`)")
    args.out.mkdir(parents=True, exist_ok=True)
    scene = Scene.load(args.scene)
    folders = recordings(args.out, args.scene, windows, seeds)
    rows = [
        row
        for label, method, models, db in methods([args.models, *args.more_models], args.database, scene)
        for row in method_rows(label, method, db, folders, scene, models)
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
