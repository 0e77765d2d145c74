"""The window model: a window's per-frame estimates in, its de-shrunk D(0, t) out (issue 17's first step).

A frame's highlights pin down only some combinations of Eq. 1's (d, p, a, b), so the per-frame network's a and b
shrink towards zero (slope 0.23-0.58) and the window's amplitude came out 42-70 % low. Over a whole window the
shape of the series (a damped oscillation), its brightness and how the per-frame values move together say more:
a small 1-D convolutional network (``training/window.py``), run here by onnxruntime, maps a window's per-frame
d, p, a, b and brightness to the correction of its steady D(0, t) (:mod:`service.analysis.steady`), which the
window fit then takes as before. Its graph is ``window.onnx`` beside the per-frame network it was trained on.

The fit's intervals see only the noise of the series it is given, not the bias the model leaves in it (or the
poles' error on a scene unlike the renderer's): :class:`Intervals`, calibrated on held-out windows of the renderer
by split conformal prediction and stored in ``window.json``, widens each window's intervals to hold the truth in
95 % of such windows.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.analysis.results import Interval, WindowResult
from service.errors import MeniscopeError
from service.inverse.manifest import sha256_file
from service.pipeline.records import LATENT_SIZE

#: File name of the window model in a model folder (it reads that folder's per-frame network's outputs).
FILE = "window.onnx"
#: Its record beside it: the sha256 of the per-frame network whose outputs it was trained on, and how it was trained.
RECORD = "window.json"
#: The per-frame graph whose outputs the window model reads.
NETWORK = "network.onnx"
#: Input and output names of the graph: features (1, FEATURES, m) -> correction (1, m), in units of SCALE_MM.
INPUT, OUTPUT = "features", "correction"
#: Scales (mm, 1, mm, mm) that bring d, p, a, b to order one; D(0, t) and its correction are in SCALE_MM.
COEFFICIENT_SCALE = np.array([0.03, 0.15, 0.02, 0.02])
SCALE_MM = 0.02
#: Relative brightness modulation is multiplied by this (a few per cent of the mean) to be of order one.
BRIGHTNESS_SCALE = 20.0
#: Frame index is divided by this (a window at 100 ejections/s and 19,000 frames/s is 190 frames).
TIME_SCALE = 200.0
#: Channels per frame: d, p, a, b, steady D(0, t), brightness, time since the window start, whether the frame
#: is in the ejection's transient, whether its values are there (missing frames are zeros).
FEATURE_NAMES = ("d", "p", "a", "b", "steady", "brightness", "time", "transient", "present")
FEATURES = len(FEATURE_NAMES)
#: The channel that says which frames are there (the model averages over them).
PRESENT = FEATURE_NAMES.index("present")
#: Channels a model may take after those: the per-frame network's latent (its encoder mean, as it comes), which
#: says more of a frame than the 5 numbers its head squeezes out of it. ``window.json``'s ``features`` names a
#: model's channels (:data:`FEATURE_NAMES`, then these or not; a record without them: the first alone).
LATENT_FEATURES = tuple(f"latent{i}" for i in range(LATENT_SIZE))


def window_features(
    coefficients: np.ndarray,
    brightness: np.ndarray,
    steady: np.ndarray,
    skip: int,
    latent: np.ndarray | None = None,
) -> np.ndarray:
    """The model's input (channels, m) float32 of one window of m frames: its per-frame coefficients (m, 4), mean
    brightness (m,), steady D(0, t) (m,, mm) and the number of transient frames at its start (``skip``): the
    :data:`FEATURES` channels; with the network's ``latent`` (m, LATENT_SIZE), its :data:`LATENT_FEATURES` after
    them (a frame without one counts as missing)."""
    c = np.asarray(coefficients, np.float64)
    m = len(c)
    present = np.isfinite(c).all(axis=1) & np.isfinite(steady) & np.isfinite(brightness)
    out = np.zeros((FEATURES + (0 if latent is None else LATENT_SIZE), m), np.float32)
    if latent is not None:
        present &= np.isfinite(latent).all(axis=1)
        out[FEATURES:] = np.where(present, np.asarray(latent, np.float32).T, 0.0)
    if not present.any():
        return out
    b = np.asarray(brightness, np.float64)
    mean = float(np.mean(b[present]))
    out[0:4] = np.where(present, (c / COEFFICIENT_SCALE).T, 0.0)
    out[4] = np.where(present, steady / SCALE_MM, 0.0)
    out[5] = np.where(present, BRIGHTNESS_SCALE * (b / mean - 1.0) if mean > 0 else 0.0, 0.0)
    out[6] = np.arange(m) / TIME_SCALE
    out[7, : min(skip, m)] = 1.0
    out[PRESENT] = present
    return out


#: The quantities whose intervals are calibrated: the modes' frequency, decay rate and amplitude, and the offset.
QUANTITIES = ("frequency", "decay", "amplitude", "offset")


#: Largest log-half-width an interval takes (a factor of 5e8 either way): finite for JSON where the fit's own is
#: many times its estimate.
_MAX_LOG_HALF = 20.0


@dataclass(frozen=True)
class Intervals:
    """Conformal intervals. A window's error scale for quantity q is s = hypot(h, floor[q] |x|) (h: the fit's own
    half-width, x: the estimate; the offset's floor is in mm, not relative), and its interval x +- factor[q] s; or,
    where ``log[q]`` (errors that are ratios: an amplitude shrunk to a third needs room up to three times itself,
    not down below zero), s = hypot(h / x, floor[q]) and the interval x exp(+-factor[q] s). The floor makes room
    for the error the fit cannot see (the series' bias); the factor is the (1 - alpha)(1 + 1/n) quantile of the
    error in units of s (|truth - x| / s, or |log(truth / x)| / s) over n held-out windows
    (``training.window_intervals``), so that the intervals hold the truth in >= 1 - alpha of windows like them."""

    factor: dict[str, float]
    floor: dict[str, float]
    log: dict[str, bool]
    windows: int
    confidence: float

    @classmethod
    def from_record(cls, record: dict) -> Intervals | None:
        """The calibration stored in a window model's record, or None where it has none."""
        stored = record.get("intervals")
        if stored is None:
            return None
        return cls(stored["factor"], stored["floor"], stored["log"], stored["windows"], stored["confidence"])

    def as_record(self) -> dict:
        return {
            "factor": self.factor,
            "floor": self.floor,
            "log": self.log,
            "windows": self.windows,
            "confidence": self.confidence,
        }

    def scale(self, quantity: str, estimate: np.ndarray, fit_half: np.ndarray) -> np.ndarray:
        """The error scale s of ``quantity`` (log units, or those of the quantity)."""
        if self.log[quantity]:
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.hypot(np.where(estimate > 0, fit_half / np.abs(estimate), np.inf), self.floor[quantity])
        magnitude = 1.0 if quantity == "offset" else np.abs(estimate)
        return np.hypot(fit_half, self.floor[quantity] * magnitude)

    def error(self, quantity: str, estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
        """How far the truth lies from the estimate, in the units of :meth:`scale`."""
        if self.log[quantity]:
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.abs(np.log(truth / estimate))
        return np.abs(truth - estimate)

    def bounds(self, quantity: str, estimate: np.ndarray, fit_half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The calibrated interval of ``quantity`` from the estimates and the fit's half-widths (same shapes)."""
        half = self.factor[quantity] * self.scale(quantity, estimate, fit_half)
        if self.log[quantity]:
            half = np.minimum(half, _MAX_LOG_HALF)
            return estimate * np.exp(-half), estimate * np.exp(half)
        low = estimate - half
        return (low if quantity == "offset" else np.maximum(low, 0.0)), estimate + half

    def _interval(self, quantity: str, estimate: float, fit: Interval | None) -> Interval | None:
        if fit is None or (self.log[quantity] and estimate <= 0):  # unbounded by the fit, or no ratio to it
            return None
        lo, hi = self.bounds(quantity, np.float64(estimate), np.float64(max(fit[1] - estimate, estimate - fit[0])))
        return (float(lo), float(hi))

    def apply(self, result: WindowResult) -> WindowResult:
        """``result`` with its modes' and offset's intervals calibrated (:attr:`WindowResult.intervals`)."""
        if result.offset_mm is None:
            return result
        modes = [
            m.model_copy(
                update={
                    "frequency_ci_hz": self._interval("frequency", m.frequency_hz, m.frequency_ci_hz),
                    "decay_rate_ci_per_s": self._interval("decay", m.decay_rate_per_s, m.decay_rate_ci_per_s),
                    "amplitude_ci_mm": self._interval("amplitude", m.amplitude_mm, m.amplitude_ci_mm),
                }
            )
            for m in result.modes
        ]
        offset = self._interval("offset", result.offset_mm, result.offset_ci_mm)
        return result.model_copy(update={"modes": modes, "offset_ci_mm": offset, "intervals": "calibrated"})


class WindowModel:
    """The window model of a model folder, run on one CPU thread (it serves one window at a time)."""

    def __init__(self, path: Path) -> None:
        import onnxruntime as ort

        from service.inverse.network import session_options

        if not path.is_file():
            raise MeniscopeError(path, "no window model here: `python -m training.window` makes one")
        record = path.with_name(RECORD)
        network = path.with_name(NETWORK)
        if not record.is_file() or not network.is_file():
            raise MeniscopeError(path, f"needs {RECORD} and {NETWORK} beside it (`python -m training.window`)")
        stored = json.loads(record.read_text())
        trained_on = stored.get("network_sha256")
        if trained_on != sha256_file(network):
            raise MeniscopeError(
                path,
                f"trained on another {NETWORK} than the one beside it: its corrections would be wrong "
                "(train it again: `python -m training.window`)",
            )
        features = tuple(stored.get("features", FEATURE_NAMES))
        if features not in (FEATURE_NAMES, FEATURE_NAMES + LATENT_FEATURES):
            raise MeniscopeError(record, f"its features {list(features)} are not ones the window model is given")
        self.path = path
        #: Whether the model takes the network's latent per frame (:data:`LATENT_FEATURES`).
        self.latent = len(features) > FEATURES
        #: The calibration of the windows' intervals (None for a model trained before it: the fit's own stay).
        self.intervals = Intervals.from_record(stored)
        self._session = ort.InferenceSession(str(path), session_options(1), providers=["CPUExecutionProvider"])
        (taken,) = [i.shape[1] for i in self._session.get_inputs() if i.name == INPUT] or [None]
        if taken != len(features):
            raise MeniscopeError(path, f"takes {taken} features per frame, not the {len(features)} {RECORD} names")

    @classmethod
    def of_folder(cls, models: Path) -> WindowModel:
        """The window model beside the per-frame network of ``models``."""
        return cls(Path(models) / FILE)

    def correct(
        self, coefficients: np.ndarray, brightness: np.ndarray, steady: np.ndarray, skip: int, latent: np.ndarray
    ) -> np.ndarray:
        """The window's steady D(0, t) (m,, mm) with the model's correction added; missing frames stay NaN.
        ``latent`` (m, LATENT_SIZE): the network's per frame, read where the model takes it (:attr:`latent`)."""
        features = window_features(coefficients, brightness, steady, skip, latent if self.latent else None)
        if len(steady) == 0 or not features[PRESENT].any():
            return steady
        correction = self._session.run([OUTPUT], {INPUT: features[None]})[0][0].astype(np.float64)
        return steady + SCALE_MM * correction
