"""Calibration of the window model's intervals (:class:`service.inverse.window_model.Intervals`) on held-out
recordings of the renderer, and their coverage on others.

Split conformal prediction: each held-out window's score is its error in units of its scale
(:class:`service.inverse.window_model.Intervals`: |error| over hypot(h, floor |estimate|), h the fit's own
half-width, or the log-ratio over hypot(h / estimate, floor)); the factor is the ceil((n + 1)(1 - alpha)) / n
quantile of the n scores, which holds the truth in >= 1 - alpha of exchangeable windows whatever the fit's errors
are. The floor (per quantity, from a short grid) and the space (linear or log) are those whose intervals come out
narrowest. Usage::

    python -m training.window_intervals --models models/default CAL1.cine CAL2.cine ...
    python -m training.window_intervals --models models/default --randomised 80 --data DIR CAL1.cine ...
    python -m training.window_intervals --models models/default --score TEST1.cine TEST2.cine ...

``--randomised N`` pools N windows per noise preset and camera from scenes randomised around the scene
(:func:`training.window.render_calibration`, rendered into ``--data`` where absent) with the named ones, so that the
intervals make room for a camera whose world is not the scene's (docs/window_model.md, "Intervals calibrated on
randomised worlds").
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from service import DEFAULT_MODELS, DEFAULT_SCENE
from service.analysis.offline import analyse_recording
from service.analysis.results import FitSettings, Report
from service.inverse import window_model as wm
from service.inverse.manifest import MANIFEST, Manifest, write_manifest
from service.scene import Scene
from service.validation.score import QUANTITIES, window_coverage, window_errors, window_pairs
from service.validation.truth import read_truth

#: The floors tried (relative to the estimate, or log units; mm for the offset): none, then shares of error the fit
#: cannot see.
FLOORS = {
    "frequency": (0.0, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05),
    "decay": (0.0, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5),
    "amplitude": (0.0, 0.02, 0.05, 0.1, 0.2, 0.5),
    "offset": (0.0, 0.0005, 0.001, 0.002, 0.005, 0.01),
}
#: window_pairs' names of the quantities, in wm.QUANTITIES' order.
PAIR_KEYS = dict(zip(wm.QUANTITIES, QUANTITIES))


def reports(recordings: list[Path], scene: Scene, models: Path) -> list[tuple[Report, dict]]:
    """Each recording analysed as ``meniscope analyze`` does by default (the network, the window model), with its
    truth."""
    out = []
    for path in recordings:
        analysis = analyse_recording(path, scene, "network", models, settings=FitSettings(), progress=False)
        out.append((analysis.report, read_truth(path)))
    return out


def pooled_pairs(analysed: list[tuple[Report, dict]]) -> dict[str, np.ndarray]:
    """:func:`window_pairs` of every recording, concatenated."""
    parts = [window_pairs(report, truth) for report, truth in analysed]
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def conformal_factor(scores: np.ndarray, confidence: float) -> float:
    """The split-conformal quantile: the ceil((n + 1) c)-th smallest of n scores (infinite where n is too small)."""
    n = scores.size
    rank = math.ceil((n + 1) * confidence)
    return float(np.sort(scores)[rank - 1]) if rank <= n else math.inf


def calibrate(pairs: dict[str, np.ndarray], confidence: float) -> wm.Intervals:
    """Per quantity the space (linear or log; the offset linear) and floor of :data:`FLOORS` whose conformal
    intervals have the smallest median half-width relative to the truth (absolute for the offset), and its factor."""
    factor, floor, log = {}, {}, {}
    windows = 0
    for quantity, key in PAIR_KEYS.items():
        est, true, lo, hi = (pairs[f"{key}_{part}"] for part in ("est", "true", "lo", "hi"))
        keep = np.isfinite(est) & np.isfinite(lo) & np.isfinite(hi)
        est, true, fit_half = est[keep], true[keep], np.maximum(hi[keep] - est[keep], est[keep] - lo[keep])
        windows = max(windows, int(keep.sum()))
        best = (math.inf, 0.0, math.inf, False)
        for in_log in (False, True) if quantity != "offset" else (False,):
            for f in FLOORS[quantity]:
                trial = wm.Intervals({quantity: 1.0}, {quantity: f}, {quantity: in_log}, 0, confidence)
                score = trial.error(quantity, est, true) / trial.scale(quantity, est, fit_half)
                k = conformal_factor(np.where(np.isnan(score), np.inf, score), confidence)
                if not math.isfinite(k):
                    continue
                calibrated = wm.Intervals({quantity: k}, {quantity: f}, {quantity: in_log}, 0, confidence)
                low, high = calibrated.bounds(quantity, est, fit_half)
                width = float(np.median((high - low) / 2 / (1.0 if quantity == "offset" else np.abs(true))))
                if width < best[0]:
                    best = (width, f, k, in_log)
        if not math.isfinite(best[2]):
            raise ValueError(f"{keep.sum()} windows with a {quantity} interval: too few to calibrate at {confidence}")
        _, floor[quantity], factor[quantity], log[quantity] = best
    return wm.Intervals(factor, floor, log, windows, confidence)


def scores(analysed: list[tuple[Report, dict]]) -> dict[str, float | None]:
    """Pooled over every window: medians and 90th percentiles of the errors, the share of intervals holding the
    truth, and the median interval half-width (relative; mm for the offset), per quantity (None without any)."""
    errors = [window_errors(r, t) for r, t in analysed]
    held = [window_coverage(r, t) for r, t in analysed]
    pairs = pooled_pairs(analysed)
    out: dict[str, float | None] = {"windows": float(sum(len(t["windows"]) for _, t in analysed))}
    for key in QUANTITIES:
        e = np.concatenate([x[key] for x in errors])
        c = np.concatenate([x[key] for x in held])
        width = (pairs[f"{key}_hi"] - pairs[f"{key}_lo"]) / 2
        width = width / (1.0 if key == "offset_mm" else np.abs(pairs[f"{key}_true"]))
        e, c, width = e[np.isfinite(e)], c[np.isfinite(c)], width[np.isfinite(width)]
        out |= {
            f"{key}_windows": float(e.size),
            f"{key}_median": _or_none(np.median, e),
            f"{key}_p90": _or_none(lambda x: np.percentile(x, 90), e),
            f"{key}_coverage": _or_none(np.mean, c),
            f"{key}_half_width_median": _or_none(np.median, width),
        }
    return out


def _or_none(statistic: Callable[[np.ndarray], float], values: np.ndarray) -> float | None:
    """``statistic`` of ``values``, None where there are none (JSON has no NaN)."""
    return float(statistic(values)) if values.size else None


def calibrate_folder(models: Path, recordings: list[Path], scene: Scene, confidence: float = 0.95) -> wm.Intervals:
    """The window model of ``models`` calibrated on ``recordings``, stored in its record; the folder's manifest
    rewritten. The recordings are analysed with a copy of the folder whose record has no intervals (so that the
    fit's own are scored): the folder itself is left as it was until the result is written, so that a failure
    loses nothing and its manifest keeps matching its files."""
    record_path = models / wm.RECORD
    record = json.loads(record_path.read_text())
    with tempfile.TemporaryDirectory(prefix="meniscope-intervals-") as scratch:
        bare = Path(scratch) / models.name
        shutil.copytree(models, bare)
        without = {key: value for key, value in record.items() if key != "intervals"}
        (bare / wm.RECORD).write_text(json.dumps(without, indent=1) + "\n")
        write_manifest(bare, Manifest.model_validate_json((bare / MANIFEST).read_text()))
        intervals = calibrate(pooled_pairs(reports(recordings, scene, bare)), confidence)
    record["intervals"] = intervals.as_record() | {"recordings": [str(r) for r in recordings]}
    record_path.write_text(json.dumps(record, indent=1) + "\n")
    write_manifest(models, Manifest.model_validate_json((models / MANIFEST).read_text()))
    return intervals


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m training.window_intervals", description=__doc__.splitlines()[0])
    p.add_argument("recordings", nargs="*", type=Path, help="simulated recordings (with .truth.json)")
    p.add_argument("--models", type=Path, default=DEFAULT_MODELS, help="model folder of the window model")
    p.add_argument("--score", action="store_true", help="score the recordings (coverage) instead of calibrating")
    p.add_argument("--scene", type=Path, default=DEFAULT_SCENE)
    p.add_argument("--out", type=Path, help="with --score: JSON of the figures")
    p.add_argument(
        "--randomised",
        type=int,
        default=0,
        metavar="N",
        help="calibrate on N more windows per noise preset and camera (12 and 8 bits) from scenes randomised around "
        "--scene, rendered into --data where absent (default 0)",
    )
    p.add_argument("--data", type=Path, default=Path("data/window"), help="folder of the --randomised windows")
    p.add_argument("--seed", type=int, default=0, help="seed of the --randomised windows (training.window's)")
    args = p.parse_args(argv)
    if args.randomised < 0:
        p.error(f"--randomised must be zero or positive, got {args.randomised}")
    if args.score and args.randomised:
        p.error("--randomised calibrates: not with --score")
    if not args.recordings and not args.randomised:
        p.error("no recordings: name some or --randomised N")
    scene = Scene.load(args.scene)
    if args.score:
        figures = scores(reports(args.recordings, scene, args.models))
        print(json.dumps(figures, indent=1))
        if args.out:
            args.out.write_text(json.dumps(figures, indent=1) + "\n")
        return
    recordings = list(args.recordings)
    if args.randomised:
        from training.window import render_calibration

        recordings += render_calibration(args.data, scene, 0, args.seed, args.randomised)
    intervals = calibrate_folder(args.models, recordings, scene)
    print(json.dumps(intervals.as_record(), indent=1))


if __name__ == "__main__":
    main()
