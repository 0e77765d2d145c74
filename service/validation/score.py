"""A report scored against the ground truth of a simulated recording (``REC.truth.json``).

What the engineers act on, per window: the dominant mode's frequency, decay rate and amplitude and
the offset ``d + p R``; what the segmentation must get right: the ejections (within a tolerance).
Relative errors are |estimate - truth| / truth; a window without a dominant mode scores NaN and is
counted as missed, not dropped.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from service.analysis.results import Report
from service.inverse.base import InverseOutput
from service.validation.truth import truth_centre, truth_coefficients


def ejection_matches(found: np.ndarray, true: np.ndarray, tolerance: int = 2) -> tuple[int, int, int]:
    """(true positives, found, true): a found ejection matches at most one true one within ``tolerance`` frames."""
    found, true = np.sort(np.asarray(found)), np.sort(np.asarray(true))
    used = np.zeros(true.size, bool)
    hits = 0
    for f in found:
        near = np.flatnonzero(~used & (np.abs(true - f) <= tolerance))
        if near.size:
            used[near[np.argmin(np.abs(true[near] - f))]] = True
            hits += 1
    return hits, int(found.size), int(true.size)


#: The scored quantities: the dominant mode's frequency, decay rate and amplitude (relative errors) and the offset.
QUANTITIES = ("frequency", "decay", "amplitude", "offset_mm")


def window_pairs(report: Report, truth: dict[str, Any]) -> dict[str, np.ndarray]:
    """Per true window (W,) and quantity: the estimate, the truth and the ends of the estimate's interval (each
    (W,), NaN where there is none). A report window is matched to the true window whose start it lies within 2
    frames of; unmatched or mode-less windows give NaN."""
    out = {
        f"{k}_{part}": np.full(len(truth["windows"]), np.nan)
        for k in QUANTITIES
        for part in ("est", "true", "lo", "hi")
    }
    starts = {w.start_frame: w for w in report.windows}

    def put(key: str, i: int, est: float, true: float, interval: tuple[float, float] | None) -> None:
        out[f"{key}_est"][i], out[f"{key}_true"][i] = est, true
        if interval is not None:
            out[f"{key}_lo"][i], out[f"{key}_hi"][i] = interval

    for i, tw in enumerate(truth["windows"]):
        match = [starts[s] for s in range(tw["start_frame"] - 2, tw["start_frame"] + 3) if s in starts]
        if not match:
            continue
        w, true = match[0], tw["truth"]
        if w.offset_mm is not None:
            put("offset_mm", i, w.offset_mm, tw["offset_mm"], w.offset_ci_mm)
        if w.modes:
            m = w.modes[0]
            put("frequency", i, m.frequency_hz, true["f1"], m.frequency_ci_hz)
            put("decay", i, m.decay_rate_per_s, true["g1"], m.decay_rate_ci_per_s)
            put("amplitude", i, m.amplitude_mm, true["A1"], m.amplitude_ci_mm)
    return out


def window_errors(report: Report, truth: dict[str, Any]) -> dict[str, np.ndarray]:
    """Per true window (W,): relative errors of the dominant frequency, decay and amplitude, offset error (mm)
    (matched as :func:`window_pairs`; NaN where unmatched or without a mode)."""
    pairs = window_pairs(report, truth)
    out = {}
    for key in QUANTITIES:
        error = np.abs(pairs[f"{key}_est"] - pairs[f"{key}_true"])
        out[key] = error if key == "offset_mm" else error / pairs[f"{key}_true"]
    return out


def window_coverage(report: Report, truth: dict[str, Any]) -> dict[str, np.ndarray]:
    """Per true window (W,) and quantity: 1.0 where the estimate's interval holds the truth, 0.0 where it does not,
    NaN where there is no estimate or no interval."""
    pairs = window_pairs(report, truth)
    out = {}
    for key in QUANTITIES:
        lo, hi, true = (pairs[f"{key}_{part}"] for part in ("lo", "hi", "true"))
        out[key] = np.where(np.isfinite(lo) & np.isfinite(hi), ((lo <= true) & (true <= hi)).astype(float), np.nan)
    return out


def error_statistics(errors: dict[str, np.ndarray]) -> dict[str, float | None]:
    """``{quantity}_median`` and ``{quantity}_p90`` of each quantity's finite errors (None where there are none)."""
    out: dict[str, float | None] = {}
    for key, values in errors.items():
        finite = np.asarray(values, np.float64)
        finite = finite[np.isfinite(finite)]
        out[f"{key}_median"] = float(np.median(finite)) if finite.size else None
        out[f"{key}_p90"] = float(np.percentile(finite, 90)) if finite.size else None
    return out


def summary(report: Report, truth: dict[str, Any], per_frame: InverseOutput | None = None) -> dict[str, Any]:
    """Medians and 90th percentiles of :func:`window_errors` (and, as ``{quantity}_errors``, the finite errors
    themselves, so that a set of recordings can be pooled over its windows), segmentation precision and recall
    (+-2 frames), and with the ``per_frame`` estimates the RMSE of each coefficient and of D(0, t), and the
    correlation of D(0, t), outside the transients."""
    errors = window_errors(report, truth)
    hits, found, true = ejection_matches(np.array(report.ejections), np.array(truth["ejections"]))
    out: dict[str, Any] = {
        "windows": len(truth["windows"]),
        "windows_with_mode": int(np.isfinite(errors["frequency"]).sum()),
        "precision": hits / found if found else None,
        "recall": hits / true if true else None,
    }
    out |= error_statistics(errors)
    out |= {f"{key}_errors": values[np.isfinite(values)].tolist() for key, values in errors.items()}
    for key, held in window_coverage(report, truth).items():  # the share of intervals that hold the truth
        finite = held[np.isfinite(held)]
        out[f"{key}_coverage"] = float(np.mean(finite)) if finite.size else None
    if per_frame is not None:
        true_coeffs = truth_coefficients(truth)
        true_centre = truth_centre(truth)
        keep = np.ones(true_centre.size, bool)
        for w in truth["windows"]:
            keep[w["start_frame"] : w["oscillation_start_frame"]] = False
        err = per_frame.centre[keep] - true_centre[keep]
        out["centre_rmse_mm"] = float(np.sqrt(np.mean(err**2)))
        out["centre_correlation"] = float(np.corrcoef(per_frame.centre[keep], true_centre[keep])[0, 1])
        rmse = np.sqrt(np.mean((per_frame.coefficients[keep] - true_coeffs[keep]) ** 2, axis=0))
        out.update({f"{name}_rmse": float(v) for name, v in zip(("d_mm", "p", "a_mm", "b_mm"), rmse)})
    return out
