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


def window_errors(report: Report, truth: dict[str, Any]) -> dict[str, np.ndarray]:
    """Per true window (W,): relative errors of the dominant frequency, decay and amplitude, offset error (mm).

    A report window is matched to the true window whose start it lies within 2 frames of; unmatched
    or mode-less windows give NaN.
    """
    keys = ("frequency", "decay", "amplitude", "offset_mm")
    out = {k: np.full(len(truth["windows"]), np.nan) for k in keys}
    starts = {w.start_frame: w for w in report.windows}
    for i, tw in enumerate(truth["windows"]):
        match = [starts[s] for s in range(tw["start_frame"] - 2, tw["start_frame"] + 3) if s in starts]
        if not match:
            continue
        w, true = match[0], tw["truth"]
        if w.offset_mm is not None:
            out["offset_mm"][i] = abs(w.offset_mm - tw["offset_mm"])
        if w.modes:
            m = w.modes[0]
            out["frequency"][i] = abs(m.frequency_hz - true["f1"]) / true["f1"]
            out["decay"][i] = abs(m.decay_rate_per_s - true["g1"]) / true["g1"]
            out["amplitude"][i] = abs(m.amplitude_mm - true["A1"]) / true["A1"]
    return out


def summary(report: Report, truth: dict[str, Any], per_frame: InverseOutput | None = None) -> dict[str, Any]:
    """Medians and 90th percentiles of :func:`window_errors`, segmentation precision and recall (+-2 frames),
    and with the ``per_frame`` estimates the RMSE of each coefficient and of D(0, t), and the correlation
    of D(0, t), outside the transients."""
    errors = window_errors(report, truth)
    hits, found, true = ejection_matches(np.array(report.ejections), np.array(truth["ejections"]))
    out: dict[str, Any] = {
        "windows": len(truth["windows"]),
        "windows_with_mode": int(np.isfinite(errors["frequency"]).sum()),
        "precision": hits / found if found else None,
        "recall": hits / true if true else None,
    }
    for key, values in errors.items():
        finite = values[np.isfinite(values)]
        out[f"{key}_median"] = float(np.median(finite)) if finite.size else None
        out[f"{key}_p90"] = float(np.percentile(finite, 90)) if finite.size else None
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
