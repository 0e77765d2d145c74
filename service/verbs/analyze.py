"""``meniscope analyze`` (a recording) and ``meniscope fit`` (a displacement series): REPORT.json, a per-frame
CSV and a PNG of the series with the fitted curves (shared/spec/cli.md)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from service.errors import MeniscopeError, require_folder_of
from service.verbs import add_scene_option


def _common(p: argparse.ArgumentParser) -> None:
    """Ejection and fit options shared by both verbs."""
    cut = p.add_mutually_exclusive_group()
    cut.add_argument("--ejection-hz", type=float, help="ejections per second, phase found from the data")
    cut.add_argument(
        "--ejections",
        type=Path,
        help="file of ejection frame indices (one per line) or CSV with a 'frame' or 'time_s' column",
    )
    p.add_argument(
        "--max-modes", type=int, default=2, choices=(0, 1, 2), help="most damped modes per window (default 2)"
    )
    p.add_argument(
        "--settle-fraction",
        type=float,
        default=0.05,
        help="settled when the envelope stays under this fraction of its start (default 0.05)",
    )
    p.add_argument(
        "--settle-floor-um",
        type=float,
        default=0.5,
        help="... or under this absolute floor in micrometres, whichever is larger (default 0.5)",
    )
    p.add_argument(
        "--transient-ms",
        type=float,
        default=0.3,
        help="time after each ejection left out of the fit: the droplet leaving (default 0.3)",
    )
    p.add_argument("--out", type=Path, required=True, help="REPORT.json to write; the CSV and PNG go beside it")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def register(subparsers: argparse._SubParsersAction) -> None:
    from service.inverse.methods import METHODS

    p = subparsers.add_parser(
        "analyze",
        help="per-frame inversion, ejection segmentation and one fit per window of a recording",
        description="Offline analysis of a recording (.cine or .avi): per-frame coefficients, ejection "
        "segmentation (detected from the video unless given), one fit per window. Writes REPORT.json, "
        "REPORT.frames.csv (t, d, p, a, b, D(0, t)) and REPORT.png.",
    )
    p.add_argument("recording", type=Path, help="REC.cine or REC.avi")
    add_scene_option(p)
    p.add_argument("--models", type=Path, help="model folder (default: the shipped models)")
    p.add_argument(
        "--method", choices=METHODS, default="network", help="inverse method (default network, the fast one)"
    )
    p.add_argument(
        "--database", type=Path, help="render database of the nearest-neighbour methods (default MODELS/database)"
    )
    p.add_argument(
        "--refine",
        action="store_true",
        help="refine each window's motion on its frames through the renderer, starting from the window model's "
        "fit (network) or the method's per-frame values: seconds per window instead of milliseconds, far more "
        "accurate decay, amplitude and offset",
    )
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="fit (and refine) the windows on the Dask cluster whose scheduler listens there "
        "(tcp://host:8786; needs the 'scale' extra) instead of local processes",
    )
    p.add_argument("--workers", type=int, help="local processes fitting windows (default: one per core)")
    p.add_argument(
        "--poles",
        choices=("frames", "series"),
        help="where each window's frequencies and decay rates come from: its frames' mean brightness "
        "(default; amplitudes, phases and offset still from D(0, t)) or D(0, t) alone (always with --refine: "
        "the refined motion is the window's inversion, its poles its own)",
    )
    p.add_argument(
        "--brightness",
        choices=("products", "modes"),
        help="how the frames' brightness gives the poles (with --poles frames): fitted as a polynomial of two "
        "damped modes (default: the brightness is nonlinear in the surface's motion and holds the modes' "
        "harmonics and sum and difference frequencies) or as damped modes alone (the fit until 2026-11-26)",
    )
    p.add_argument(
        "--series",
        choices=("steady", "window"),
        help="the series each window is fitted to: the steady D(0, t) of the per-frame estimates or that "
        "corrected by the model folder's window model (window.onnx), which undoes the shrink of the per-frame "
        "amplitudes; window is the network method's only (default: window with it, steady otherwise)",
    )
    _common(p)
    p.set_defaults(func=run_analyze)

    p = subparsers.add_parser(
        "fit",
        help="the window fit alone on a displacement series",
        description="Fit a displacement series (CSV, one value per frame, header 'value'; empty cells are "
        "missing samples). Without ejections the whole series is one window. Writes FIT.json and FIT.png.",
    )
    p.add_argument("series", type=Path, help="SERIES.csv")
    p.add_argument("--fps", type=float, required=True, help="frames per second of the series")
    p.add_argument("--column", default="value", help="column holding the series (default 'value')")
    _common(p)
    p.set_defaults(func=run_fit)


def _settings(args: argparse.Namespace, poles: str = "series"):
    """The fit settings the options ask for, the windows' poles from ``poles`` ("frames" or "series")."""
    from service.analysis.results import FitSettings

    for name, value in (
        ("--settle-fraction", args.settle_fraction),
        ("--settle-floor-um", args.settle_floor_um),
        ("--transient-ms", args.transient_ms),
    ):
        if not math.isfinite(value) or value < 0:
            raise MeniscopeError(name, f"must be a finite non-negative number, got {value}")
    if args.ejection_hz is not None and not (math.isfinite(args.ejection_hz) and args.ejection_hz > 0):
        raise MeniscopeError("--ejection-hz", f"must be a positive number, got {args.ejection_hz}")
    if not 0 < args.settle_fraction < 1:
        raise MeniscopeError("--settle-fraction", f"must lie between 0 and 1, got {args.settle_fraction}")
    return FitSettings(
        max_modes=args.max_modes,
        settle_fraction=args.settle_fraction,
        settle_floor_mm=args.settle_floor_um * 1e-3,
        transient_s=args.transient_ms * 1e-3,
        poles=poles,
    )


def _outputs(out: Path) -> tuple[Path, Path, Path]:
    """REPORT.json and the CSV and PNG named after it."""
    if out.suffix.lower() != ".json":
        raise MeniscopeError(out, "the report must be a .json file")
    require_folder_of(out)
    return out, out.with_suffix(".frames.csv"), out.with_suffix(".png")


def _print_summary(report, paths: tuple[Path, ...]) -> None:
    from collections import Counter

    counts = Counter(w.status for w in report.windows)
    print(
        f"{report.source.path}: {len(report.windows)} windows ({', '.join(f'{n} {s}' for s, n in counts.items())}), "
        f"{len(report.ejections)} ejections; wrote {', '.join(str(p) for p in paths)}"
    )


def run_analyze(args: argparse.Namespace) -> int:
    from service import DEFAULT_MODELS
    from service.analysis.offline import Ejections, analyse_recording, write_per_frame
    from service.analysis.plot import plot_report
    from service.scene import Scene
    from service.simulate import truth_path
    from service.validation.truth import read_truth, truth_centre

    if args.refine and args.poles == "frames":
        raise MeniscopeError("--poles", "frames cannot be used with --refine: a refined window's poles are its own")
    if args.workers is not None and args.workers < 1:
        raise MeniscopeError("--workers", f"must be at least 1, got {args.workers}")
    if args.series == "window" and (args.method != "network" or args.refine):
        raise MeniscopeError(
            "--series",
            "window reads the network method's per-frame values: not with --method "
            f"{args.method}{' --refine' if args.refine else ''}",
        )
    settings = _settings(args, args.poles or "frames")  # with --refine, analyse_recording takes the series' own
    if args.series:
        settings = settings.model_copy(update={"series_model": args.series})
    if args.brightness:
        settings = settings.model_copy(update={"brightness_model": args.brightness})
    report_path, csv_path, png_path = _outputs(args.out)
    scene = Scene.load(args.scene)
    analysis = analyse_recording(
        args.recording,
        scene,
        args.method,
        args.models or DEFAULT_MODELS,
        args.database,
        Ejections(args.ejections, args.ejection_hz),
        settings,
        progress=not args.quiet,
        refine=args.refine,
        scheduler=args.scheduler,
        workers=args.workers,
    )
    report = analysis.report
    report.write(report_path)
    write_per_frame(csv_path, analysis.per_frame, report.source.fps)
    sidecar = truth_path(args.recording)
    truth = truth_centre(read_truth(args.recording)) if sidecar.exists() else None
    plot_report(report, analysis.fitted, png_path, truth)
    _print_summary(report, (report_path, csv_path, png_path))
    return 0


def run_fit(args: argparse.Namespace) -> int:
    import numpy as np

    from service.analysis.fit import model_curve
    from service.analysis.offline import Ejections, analyse_series
    from service.analysis.plot import plot_report
    from service.analysis.results import Source
    from service.csvtable import read_columns, write_columns
    from service.recordings.digest import xxh3_file

    if not (math.isfinite(args.fps) and args.fps > 0):
        raise MeniscopeError("--fps", f"must be a positive number, got {args.fps}")
    settings = _settings(args)
    report_path, csv_path, png_path = _outputs(args.out)
    values = read_columns(args.series, (args.column,), allow_empty=True)[:, 0]
    if values.size == 0:
        raise MeniscopeError(args.series, f"no rows in column {args.column!r}")
    source = Source(path=str(args.series), frames=values.size, fps=args.fps, xxh3_128=xxh3_file(args.series))
    report = analyse_series(
        values, args.fps, source, Ejections(args.ejections, args.ejection_hz), settings, progress=not args.quiet
    )
    report.write(report_path)
    fitted = np.full(values.size, np.nan)
    for w in report.windows:
        frames = np.arange(w.start_frame, w.end_frame)
        fitted[frames] = model_curve(w, (frames - w.start_frame) / args.fps)
    write_columns(
        csv_path,
        ("frame", "t_s", "value", "fitted_mm"),
        [np.arange(values.size), np.arange(values.size) / args.fps, values, fitted],
        "fitted series",
    )
    plot_report(report, values, png_path)
    _print_summary(report, (report_path, csv_path, png_path))
    return 0
