"""Ground truth of simulated recordings (scene.md, "Recordings and ground truth") and per-frame scores against it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.inverse.manifest import Scores
from service.jsonfile import read_schema_json
from service.physics import WindowMotion, centre_displacement
from service.scene import Scene
from service.simulate import SCHEMA, Transient, truth_path

#: Per-frame targets, in order: Eq. 1's d (mm), p (-), a (mm), b (mm), then D(0, t) (mm).
TARGETS = ("d", "p", "a", "b", "centre")


@dataclass(frozen=True)
class TruthWindow:
    """The oscillating part of one window: recording frame indices (m,), true targets (m, 5) in
    :data:`TARGETS` order, and the window's true motion."""

    frames: np.ndarray
    targets: np.ndarray
    motion: WindowMotion


def read_truth(recording: str | Path) -> dict:
    """The ``.truth.json`` beside a recording; a one-line error when it is missing or not a truth file."""
    return read_schema_json(
        truth_path(recording), SCHEMA, "not a simulated recording (`meniscope simulate` writes one)"
    )


def truth_coefficients(truth: dict) -> np.ndarray:
    """True d, p, a, b (Eq. 1) of every frame of the recording, shape (frames, 4), transients included."""
    fps = truth["recording"]["fps"]
    coeffs = np.full((truth["recording"]["frames"], 4), np.nan)
    bulge_profile = Transient().profile(truth["transient"]["frames"])
    for w in truth["windows"]:
        frames = np.arange(w["start_frame"], w["end_frame"])
        coeffs[frames] = WindowMotion(**w["truth"]).coefficients((frames - w["start_frame"]) / fps).to_array()
        bulge = frames < w["oscillation_start_frame"]
        coeffs[frames[bulge], 2] += w["bulge_mm"] * bulge_profile[frames[bulge] - w["start_frame"]]
    return coeffs


def truth_centre(truth: dict) -> np.ndarray:
    """True D(0, t) = d + p R + a + b (mm) of every frame, shape (frames,)."""
    return centre_displacement(*truth_coefficients(truth).T, truth["scene"]["nozzle"]["radius_mm"])


def truth_windows(truth: dict, scene: Scene) -> list[TruthWindow]:
    """Every window of a simulated recording, from the frame after its ejection's transient to its end.

    Only frames after the transient: the ejection's bulge lies outside the coefficient ranges the
    models are trained on and the databases hold.
    """
    radius = scene.nozzle.radius_mm
    coeffs = truth_coefficients(truth)
    windows = []
    for window in truth["windows"]:
        idx = np.arange(window["oscillation_start_frame"], window["end_frame"])  # (m,)
        c = coeffs[idx]
        targets = np.column_stack([c, centre_displacement(*c.T, radius)])
        windows.append(TruthWindow(idx, targets, WindowMotion(**window["truth"])))
    return windows


def oscillation_truth(truth: dict, scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Frame indices (M,) and true targets (M, 5) of all windows' oscillating frames (:func:`truth_windows`)."""
    windows = truth_windows(truth, scene)
    return np.concatenate([w.frames for w in windows]), np.concatenate([w.targets for w in windows])


def score(pred: np.ndarray, true: np.ndarray) -> Scores:
    """Per-target RMSE and the centre displacement's correlation, of predictions and truths (N, 5)."""
    err = np.sqrt(np.mean((pred.astype(np.float64) - true) ** 2, axis=0))  # (5,)
    p, t = pred[:, 4].astype(np.float64), true[:, 4].astype(np.float64)
    corr = float(np.corrcoef(p, t)[0, 1]) if len(p) > 1 and p.std() > 0 and t.std() > 0 else None
    return Scores(frames=len(pred), rmse={k: float(v) for k, v in zip(TARGETS, err)}, centre_correlation=corr)
