"""Every inverse method on a recording with known motion: per-frame outputs, scores, search and fit costs.

The methods (Price et al. 2022, Sec. 3.2 and Figs. 9, 10, 14): the exported networks of a model folder
(``network``: VAE encoder + regressor; ``direct``: the end-to-end CNN), and for each render database
the exact nearest neighbour, the approximate one (PCA + FLANN) and the regularised fit per window
through the exact search's k nearest candidates. Only the oscillating frames of each window are scored
(:func:`service.validation.truth.truth_windows`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from service.analysis.offline import CANDIDATES
from service.errors import MeniscopeError
from service.inverse.base import InverseMethod
from service.inverse.manifest import Scores
from service.inverse.nearest import NearestDatabase, Neighbours, recall_at_k
from service.inverse.regularised import chosen_rows
from service.recordings.roi import read_roi_frames
from service.scene import Scene
from service.validation.truth import TruthWindow, read_truth, score, truth_windows


@dataclass(frozen=True)
class MethodResult:
    """One method on one recording: predictions (M, 5) of the scored frames, its scores and its cost.

    ``oscillation``: RMSE (mm) and correlation of D(0, t) with each window's mean taken out of both
    prediction and truth, i.e. how well the motion inside a window is followed; the whole-recording
    correlation of ``scores`` is dominated by the offsets d + p R that differ from window to window.
    """

    pred: np.ndarray
    scores: Scores
    oscillation: dict[str, float | None]
    seconds_per_frame: float

    def as_json(self) -> dict[str, Any]:
        return {
            **self.scores.model_dump(mode="json"),
            "oscillation": self.oscillation,
            "seconds_per_frame": self.seconds_per_frame,
        }


@dataclass
class RecordingResult:
    """Everything measured on one recording; ``truth`` (M, 5) and ``frames`` (M,) of the scored frames."""

    path: Path
    fps: float
    renderer: str
    windows: list[TruthWindow]
    truth: np.ndarray
    frames: np.ndarray
    methods: dict[str, MethodResult] = field(default_factory=dict)
    search: dict[str, dict[str, float]] = field(default_factory=dict)  # database -> search costs and recall
    window_fits: dict[str, dict[str, float]] = field(default_factory=dict)  # regularised method -> fit errors

    def as_json(self) -> dict[str, Any]:
        return {
            "path": str(self.path),
            "fps": self.fps,
            "renderer": self.renderer,
            "windows": len(self.windows),
            "frames_scored": len(self.frames),
            "methods": {k: m.as_json() for k, m in self.methods.items()},
            "search": self.search,
            "window_fits": self.window_fits,
        }


def window_detrended(values: np.ndarray, lengths: list[int]) -> np.ndarray:
    """Values (M,) of consecutive windows of ``lengths`` with each window's mean subtracted."""
    starts = np.cumsum([0, *lengths[:-1]])
    return values - np.repeat(np.add.reduceat(values, starts) / np.asarray(lengths), lengths)


def _relative_errors(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.abs(estimate - truth) / np.abs(truth)


class Evaluation:
    """Inverse methods to compare on recordings of one scene: ``networks`` by name, ``databases`` by label."""

    def __init__(self, scene: Scene, networks: dict[str, InverseMethod], databases: dict[str, NearestDatabase]) -> None:
        self.scene, self.networks, self.databases = scene, networks, databases

    def steps(self) -> int:
        """Progress-bar steps per recording: reading, each network, each database."""
        return 1 + len(self.networks) + len(self.databases)

    def recording(self, path: Path, bar: tqdm) -> RecordingResult:
        """Run and score every method on a simulated recording (with its ``.truth.json``)."""
        truth = read_truth(path)
        if truth.get("scene_sha256") != self.scene.sha256:
            raise MeniscopeError(
                path,
                f"simulated for scene {str(truth.get('scene_sha256'))[:12]}, not this one ({self.scene.sha256[:12]})",
            )
        windows = truth_windows(truth, self.scene)
        bar.set_description(f"validate {path.name}: read")
        frames, facts = read_roi_frames(path, self.scene)
        index = np.concatenate([w.frames for w in windows])  # (M,)
        if index.max(initial=-1) >= len(frames):
            raise MeniscopeError(path, f"holds {len(frames)} frames, its truth file scores up to frame {index.max()}")
        result = RecordingResult(
            path=path,
            fps=float(facts["fps"]),
            renderer=str(truth.get("renderer", "Renderer")),
            windows=windows,
            truth=np.concatenate([w.targets for w in windows]),
            frames=index,
        )
        x = frames[index]  # (M, H, W) as stored
        bar.update()
        for name, method in self.networks.items():
            bar.set_description(f"validate {path.name}: {name}")
            started = time.perf_counter()
            out = method.infer(x)
            self._add(result, name, np.column_stack([out.coefficients, out.centre]), time.perf_counter() - started)
            bar.update()
        for label, database in self.databases.items():
            bar.set_description(f"validate {path.name}: database {label}")
            self._nearest(result, label, database, x)
            bar.update()
        return result

    def _add(self, result: RecordingResult, name: str, pred: np.ndarray, seconds: float) -> None:
        lengths = [len(w.frames) for w in result.windows]
        p, t = window_detrended(pred[:, 4], lengths), window_detrended(result.truth[:, 4], lengths)
        corr = float(np.corrcoef(p, t)[0, 1]) if p.std() > 0 and t.std() > 0 else None
        oscillation = {"rmse": float(np.sqrt(np.mean((p - t) ** 2))), "correlation": corr}
        result.methods[name] = MethodResult(pred, score(pred, result.truth), oscillation, seconds / len(pred))

    def _nearest(self, result: RecordingResult, label: str, database: NearestDatabase, x: np.ndarray) -> None:
        """Exact, approximate and regularised nearest neighbours of one database, their costs and recall@10 (:data:`CANDIDATES`)."""
        found: dict[bool, Neighbours] = {}
        seconds: dict[bool, float] = {}
        for exact in (True, False):
            started = time.perf_counter()
            found[exact] = database.search(x, k=CANDIDATES, exact=exact)
            seconds[exact] = time.perf_counter() - started
        for exact, name in ((True, "nearest"), (False, "nearest-approx")):
            first = found[exact].index[:, 0]
            pred = np.column_stack([database.coeffs[first], database.centre[first]])
            self._add(result, f"{name}[{label}]", pred, seconds[exact])
        result.search[label] = {
            "k": CANDIDATES,
            "exact_ms_per_frame": 1e3 * seconds[True] / len(x),
            "approximate_ms_per_frame": 1e3 * seconds[False] / len(x),
            "recall_at_k": recall_at_k(found[False], found[True]),
        }
        self._regularised(result, label, database, found[True], seconds[True])

    def _regularised(
        self, result: RecordingResult, label: str, database: NearestDatabase, exact: Neighbours, search_seconds: float
    ) -> None:
        """The regularised fit per window through its frames' exact candidates: per frame the fitted curve's
        D(0, t) and the coefficients of the candidate it chose; per window its frequency and decay errors."""
        pred, fps = np.empty((len(result.frames), 5)), result.fps
        fits, fit_seconds, start = [], [], 0
        for k, window in enumerate(result.windows):
            rows = slice(start, start + len(window.frames))
            started = time.perf_counter()
            chosen, fit = chosen_rows(exact.index[rows], database.centre, fps, seed=k)
            fit_seconds.append(time.perf_counter() - started)
            pred[rows, :4] = database.coeffs[chosen]
            pred[rows, 4] = fit.curve(np.arange(len(window.frames)) / fps)
            fits.append((fit.frequency_hz, fit.decay_rate_per_s, window.motion.f1, window.motion.g1))
            start = rows.stop
        name = f"regularised[{label}]"
        self._add(result, name, pred, search_seconds + sum(fit_seconds))
        f, g, f_true, g_true = np.array(fits).T
        result.window_fits[name] = {
            "windows": len(fits),
            "frequency_rel_error_median": float(np.median(_relative_errors(f, f_true))),
            "decay_rel_error_median": float(np.median(_relative_errors(g, g_true))),
            "fit_seconds_per_window_median": float(np.median(fit_seconds)),
            "search_and_fit_seconds_per_window": (search_seconds + sum(fit_seconds)) / len(fits),
        }
