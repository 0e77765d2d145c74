"""``meniscope bench fit``: our window fit against harminv on the same windows, accuracy and time side by side.

Windows are drawn as ``meniscope simulate`` draws them (two damped modes, offset, 190 frames at
19,000 frames/s) and sampled exactly, plus white noise at each level asked for. Both methods see
the same series; each is scored on the dominant (true mode 1) frequency and decay rate, a window
counting as missed when the method reports no mode within 5 % of the true frequency.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from service.analysis.fit import fit_window
from service.analysis.peer import available, harminv_modes
from service.errors import MeniscopeError, require_folder_of
from service.simulate import WindowRanges

FPS, FRAMES = 19000.0, 190
#: Noise levels (mm, standard deviation) measured by default: none, 0.2 um, 1 um.
NOISE_MM = "0,0.0002,0.001"


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("fit", help="the window fit vs harminv: accuracy and time per window", description=__doc__)
    p.add_argument("--windows", type=int, default=300, help="windows per noise level (default 300)")
    p.add_argument("--noise-mm", default=NOISE_MM, help=f"noise levels in mm, comma-separated (default {NOISE_MM})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("bench-fit.json"), help="JSON of the results")
    p.set_defaults(func=run)


def draw_windows(n: int, noise_mm: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, FRAMES) series in mm and (n, 2) true dominant (frequency Hz, decay 1/s)."""
    rng = np.random.default_rng(seed)
    ranges = WindowRanges().for_fps(FPS)
    t = np.arange(FRAMES) / FPS
    series, truth = np.empty((n, FRAMES)), np.empty((n, 2))
    for i in range(n):
        w = ranges.sample(rng)
        series[i] = w.coefficients(t).centre(1.0) + rng.normal(0.0, noise_mm, FRAMES)
        truth[i] = w.f1, w.g1
    return series, truth


def _dominant_errors(found: list[tuple[float, float]], f: float, g: float) -> tuple[float, float]:
    """Relative frequency and decay errors of the found mode nearest the true frequency; NaN if none within 5 %."""
    if not found:
        return np.nan, np.nan
    fm, gm = min(found, key=lambda m: abs(m[0] - f))
    if abs(fm - f) > 0.05 * f:
        return np.nan, np.nan
    return abs(fm - f) / f, abs(gm - g) / g


def measure(series: np.ndarray, truth: np.ndarray, method: str) -> dict:
    """Per-window time and dominant-mode errors of ``method`` ("ours" or "harminv") on every window."""
    times, errors = [], []
    for y, (f, g) in zip(tqdm(series, desc=method, unit="window", leave=False), truth):
        start = time.perf_counter()
        if method == "ours":
            found = [(m.frequency_hz, m.decay_rate_per_s) for m in fit_window(y, FPS).modes]
        else:
            found = [(m.frequency_hz, m.decay_rate_per_s) for m in harminv_modes(y, FPS, 50.0)]
        times.append(time.perf_counter() - start)
        errors.append(_dominant_errors(found, f, g))
    e = np.array(errors)
    ok = np.isfinite(e[:, 0])
    pct = lambda v, q: float(np.percentile(v, q)) if v.size else None  # noqa: E731
    return {
        "ms_per_window_median": 1e3 * float(np.median(times)),
        "found": int(ok.sum()), "windows": len(series),
        "frequency_error_median": pct(e[ok, 0], 50), "frequency_error_p90": pct(e[ok, 0], 90),
        "decay_error_median": pct(e[ok, 1], 50), "decay_error_p90": pct(e[ok, 1], 90),
    }


def compare(noise_mm: list[float], windows: int, seed: int) -> dict:
    """Ours and (when installed) harminv on ``windows`` fresh windows per noise level (seeds ``seed``, ``seed + 1``...)."""
    methods = ["ours", "harminv"] if available() else ["ours"]
    results: dict = {"fps": FPS, "frames": FRAMES, "levels": []}
    for k, noise in enumerate(noise_mm):
        series, truth = draw_windows(windows, noise, seed + k)
        fit_window(series[0], FPS)  # warm-up: imports and first-call costs are not a window's
        results["levels"].append({"noise_mm": noise, "methods": {m: measure(series, truth, m) for m in methods}})
    return results


def markdown(results: dict) -> str:
    """One row per noise level and method."""
    lines = ["| noise (mm) | method | ms/window (median) | dominant found | frequency error median / p90 | "
             "decay error median / p90 |", "|---|---|---|---|---|---|"]
    fmt = lambda v: "n/a" if v is None else f"{100 * v:.3g} %"  # noqa: E731
    for level in results["levels"]:
        for name, r in level["methods"].items():
            lines.append(f"| {level['noise_mm']:g} | {name} | {r['ms_per_window_median']:.3g} | {r['found']}/{r['windows']} | "
                         f"{fmt(r['frequency_error_median'])} / {fmt(r['frequency_error_p90'])} | "
                         f"{fmt(r['decay_error_median'])} / {fmt(r['decay_error_p90'])} |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    try:
        levels = [float(v) for v in args.noise_mm.split(",")]
    except ValueError:
        raise MeniscopeError("--noise-mm", f"expected comma-separated numbers, got {args.noise_mm!r}") from None
    if args.windows < 1 or any(not np.isfinite(v) or v < 0 for v in levels):
        raise MeniscopeError("--noise-mm", "windows must be >= 1 and noise levels finite and >= 0")
    require_folder_of(args.out)
    results = compare(levels, args.windows, args.seed)
    args.out.write_text(json.dumps(results, indent=2, allow_nan=False) + "\n")
    table = markdown(results)
    args.out.with_suffix(".md").write_text(table)
    print(table)
    return 0
