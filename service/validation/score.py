"""A report scored against the ground truth of a simulated recording (``REC.truth.json``).

What the engineers act on, per window: the dominant mode's frequency, decay rate and amplitude, the
offset ``d + p R`` and whether the meniscus settled; what the segmentation must get right: the ejections (within a
tolerance).
Relative errors are |estimate - truth| / truth; a window without a dominant mode scores NaN and is
counted as missed, not dropped.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from service.analysis.results import Report, WindowResult
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
        w, true = _matched(starts, tw), tw["truth"]
        if w is None:
            continue
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


def window_settled(report: Report, truth: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Per true window (W,): whether the meniscus settled by the window's end (Eq. 1's envelope A1 e^(-g1 t) + A2
    e^(-g2 t) at its end within max(``settle_fraction`` (A1 + A2), ``settle_floor_mm``), the report's own
    tolerance), 1 or 0, and the matched report window's verdict (-1 where unmatched: matched as
    :func:`window_pairs`)."""
    settings, fps = report.fit, report.source.fps
    starts = {w.start_frame: w for w in report.windows}
    true, said = np.zeros(len(truth["windows"]), np.int64), np.full(len(truth["windows"]), -1, np.int64)
    for i, tw in enumerate(truth["windows"]):
        m = tw["truth"]
        t = (tw["end_frame"] - tw["oscillation_start_frame"]) / fps
        left = m["A1"] * np.exp(-m["g1"] * t) + m["A2"] * np.exp(-m["g2"] * t)
        true[i] = left <= max(settings.settle_fraction * (m["A1"] + m["A2"]), settings.settle_floor_mm)
        w = _matched(starts, tw)
        if w is not None:
            said[i] = bool(w.settled)
    return true, said


def _matched(starts: dict[int, WindowResult], window: dict[str, Any]) -> WindowResult | None:
    """The report window (by start frame) whose start lies within 2 frames of the true ``window``'s, or None."""
    match = [starts[s] for s in range(window["start_frame"] - 2, window["start_frame"] + 3) if s in starts]
    return match[0] if match else None


def settling_statistics(true: np.ndarray, said: np.ndarray) -> dict[str, float | None]:
    """The share of windows whose settled verdict is the truth's (``settled_right``; a window the report has not
    counts as wrong) and the share of unsettled windows reported settled (``settled_falsely``: the error that tells
    an engineer to go on too soon); None where there is no window to count."""
    unsettled = true == 0
    return {
        "settled_right": float(np.mean(said == true)) if true.size else None,
        "settled_falsely": float(np.mean(said[unsettled] == 1)) if unsettled.any() else None,
    }


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
    true, said = window_settled(report, truth)
    out |= settling_statistics(true, said) | {"settled_true": true.tolist(), "settled_said": said.tolist()}
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
