"""What a window analysis reports (shared/spec/cli.md, "REPORT.json"): one type per noun.

The same frozen pydantic objects go to REPORT.json, REST, WebSocket, ZeroMQ and SQLite. Every
number they hold is finite: an optional quantity that arrives as NaN or Infinity becomes null
and the window's ``reason`` says which one; a required quantity that is not finite is refused.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from service.errors import MeniscopeError

#: The ``schema`` value of every report this version writes.
SCHEMA = "meniscope.report/1"

Status = Literal["ok", "settled", "unresolved", "failed"]
Finite = Annotated[float, Field(allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Interval = tuple[Finite, Finite]


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class FitSettings(_Frozen):
    """How windows are fitted and judged; stored in every report so that its numbers can be reproduced."""

    max_modes: Annotated[int, Field(ge=0, le=2)] = 2
    loss: Literal["soft_l1", "linear"] = "soft_l1"
    criterion: Literal["BIC"] = "BIC"
    confidence: Annotated[float, Field(gt=0, lt=1)] = 0.95
    #: Settling tolerance: this fraction of the window's initial envelope ...
    settle_fraction: Annotated[float, Field(gt=0, lt=1)] = 0.05
    #: ... but never below this absolute floor (mm); 0.5 um is ~1/20 pixel in the example scene.
    settle_floor_mm: NonNegative = 5e-4
    #: Time after an ejection that shows the droplet leaving, not the meniscus oscillating: those frames are
    #: left out of the fit (t still counts from the ejection). The simulator's transient lasts 0.25 ms.
    transient_s: NonNegative = 3e-4
    #: Where each window's poles (its modes' frequencies and decay rates) come from: the fitted series itself, or
    #: the window's frames (their mean brightness, which the surface's motion modulates with the same poles and
    #: far less noise than a per-frame estimate of the shape; it says nothing of amplitude or offset, which
    #: the series gives). A window whose frames show no resolved oscillation falls back to the series.
    poles: Literal["series", "frames"] = "frames"
    #: The series each window is fitted to: the steady D(0, t) of its per-frame estimates ("steady"), or that
    #: corrected by the model folder's window model (``window.onnx``, :mod:`service.inverse.window_model`), which
    #: undoes the shrink of the per-frame amplitudes from the whole window's estimates and brightness: on Blender
    #: recordings it took the amplitude error from ~70 % to ~25 % and the offset's from ~20 um to ~4 um, median).
    #: The network method's only: the other methods' windows keep their steady series.
    series_model: Literal["steady", "window"] = "window"
    #: How the frames' brightness gives the poles (with ``poles == "frames"``): as damped modes ("modes"), or as a
    #: polynomial of the two modes ("products", :mod:`service.analysis.products`), whose harmonics and sum and
    #: difference frequencies the brightness' nonlinearity adds and which biased the modes' decay rates.
    brightness_model: Literal["modes", "products"] = "products"
    #: Time after an ejection whose frames' brightness the polynomial fit leaves out (``brightness_model ==
    #: "products"``), at least :attr:`transient_s`: the ejection's light lingers after the surface is back to its
    #: modes (docs/benchmarks.md). The damped modes that start it keep :attr:`transient_s`: fewer frames left
    #: them on noise in heavily damped windows.
    brightness_transient_s: NonNegative = 5e-4

    def brightness_frames(self, fps: float) -> int:
        """Frames after an ejection whose brightness the poles' fit leaves out (rounded up)."""
        return int(np.ceil(max(self.brightness_transient_s, self.transient_s) * fps - 1e-9))

    def transient_frames(self, fps: float) -> int:
        """Frames after an ejection that :attr:`transient_s` covers (rounded up)."""
        return int(np.ceil(self.transient_s * fps - 1e-9))


class ModeEstimate(_Frozen):
    """One damped mode ``A exp(-g t) cos(2 pi f t + phi)`` of the centre displacement (Eq. 1), t from the window start."""

    frequency_hz: NonNegative
    decay_rate_per_s: NonNegative
    amplitude_mm: NonNegative
    phase_rad: Finite
    frequency_ci_hz: Interval | None = None
    decay_rate_ci_per_s: Interval | None = None
    #: The amplitude's interval at FitSettings.confidence (as the other two: see WindowResult.intervals).
    amplitude_ci_mm: Interval | None = None
    #: zeta = g / sqrt(g^2 + (2 pi f)^2) of the equivalent damped oscillator.
    damping_ratio: Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)] | None = None
    #: Q = 1 / (2 zeta); null for an undamped mode (Q infinite).
    quality_factor: NonNegative | None = None


_MODE_OPTIONAL = ("frequency_ci_hz", "decay_rate_ci_per_s", "amplitude_ci_mm", "damping_ratio", "quality_factor")
_WINDOW_OPTIONAL = (
    "offset_mm",
    "offset_ci_mm",
    "drift_mm_per_s",
    "settling_time_s",
    "residual_amplitude_mm",
    "r2",
    "noise_mm",
)


def _finite(value: Any) -> bool:
    """False for a float (or a pair of floats) that is NaN or infinite; True otherwise."""
    if isinstance(value, (tuple, list)):
        return all(_finite(v) for v in value)
    return not (isinstance(value, float) and not math.isfinite(value))


class WindowResult(_Frozen):
    """The fit of one window between ejections: modes (dominant first), offset, settling, status."""

    index: Annotated[int, Field(ge=0)]
    start_frame: Annotated[int, Field(ge=0)]
    end_frame: Annotated[int, Field(ge=0)]  # exclusive
    status: Status
    reason: str | None = None
    modes: list[ModeEstimate] = []
    offset_mm: Finite | None = None
    #: The offset's interval at FitSettings.confidence.
    offset_ci_mm: Interval | None = None
    #: Where the intervals (the modes' and the offset's) come from: the fit's covariance alone ("fit": noise only,
    #: blind to the bias of the series it was given), that scaled by the window model's calibration on held-out
    #: windows of the renderer ("calibrated", :mod:`service.inverse.window_model`), or a refined window's pixel fit
    #: ("pixels": its cluster-robust covariance, :func:`service.inverse.synthesis.covariance`); null without intervals.
    intervals: Literal["fit", "calibrated", "pixels"] | None = None
    drift_mm_per_s: Finite | None = None
    settling_time_s: NonNegative | None = None
    settled: bool = False
    #: Fitted envelope at the window's end: the amplitude the next ejection meets.
    residual_amplitude_mm: NonNegative | None = None
    r2: Finite | None = None
    #: Robust noise level of the fit residuals (1.4826 MAD).
    noise_mm: NonNegative | None = None
    #: Where the modes' frequencies and decay rates came from (FitSettings.poles); null without modes.
    poles_from: Literal["series", "frames"] | None = None
    samples: Annotated[int, Field(ge=0)] = 0  # finite samples fitted
    missing: Annotated[int, Field(ge=0)] = 0  # non-finite samples skipped
    transient_frames: Annotated[int, Field(ge=0)] = 0  # frames after the ejection left out (FitSettings.transient_s)
    starts_at_ejection: bool = False
    ends_at_ejection: bool = False

    @model_validator(mode="before")
    @classmethod
    def _non_finite_to_null(cls, data: Any) -> Any:
        """Optional numbers that are NaN/Inf become null; the reason names each one."""
        if not isinstance(data, dict):
            return data
        data, notes = dict(data), []
        for key in _WINDOW_OPTIONAL:
            if not _finite(data.get(key)):
                data[key] = None
                notes.append(f"{key} not finite")
        modes = []
        for k, mode in enumerate(data.get("modes") or [], start=1):
            if isinstance(mode, dict):
                mode = dict(mode)
                for key in _MODE_OPTIONAL:
                    if not _finite(mode.get(key)):
                        mode[key] = None
                        notes.append(f"mode {k} {key} not finite")
            modes.append(mode)
        if "modes" in data:
            data["modes"] = modes
        if notes:
            data["reason"] = "; ".join([r for r in [data.get("reason")] if r] + notes)
        return data

    @model_validator(mode="after")
    def _consistent(self) -> WindowResult:
        if self.end_frame < self.start_frame or (self.end_frame == self.start_frame and self.status != "failed"):
            raise ValueError(
                f"end_frame {self.end_frame} must exceed start_frame {self.start_frame} "
                "(only a failed window may be empty)"
            )
        if self.status != "ok" and not self.reason:
            raise ValueError(f"status {self.status!r} needs a reason")
        if self.status in ("settled", "failed") and self.modes:
            raise ValueError(f"a {self.status!r} window reports no modes")
        decays = [m.decay_rate_per_s for m in self.modes]
        if decays != sorted(decays):
            raise ValueError("modes must be ordered dominant (smallest decay rate) first")
        if self.settled != (self.settling_time_s is not None):
            raise ValueError("settling_time_s is null exactly when the window did not settle")
        return self


class Source(_Frozen):
    """What was analysed: a recording (with its frame size) or a series (width and height null)."""

    path: str
    frames: Annotated[int, Field(ge=0)]
    fps: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    width: Annotated[int, Field(gt=0)] | None = None
    height: Annotated[int, Field(gt=0)] | None = None
    #: hex XXH3-128 of the file (:mod:`service.recordings.digest`; ``xxhsum -H2`` checks it)
    xxh3_128: str | None = None
    #: hex BLAKE3 of the file, in reports written before the XXH3-128 digest (``b3sum`` checks it)
    blake3: str | None = None
    #: hex SHA-256 of the file, in reports written before the BLAKE3 digest
    sha256: str | None = None


class Report(_Frozen):
    """REPORT.json (schema ``meniscope.report/1``): one analysed source, its ejections and windows."""

    schema_: Literal["meniscope.report/1"] = Field(SCHEMA, alias="schema")
    source: Source
    method: str
    ejections: list[Annotated[int, Field(ge=0)]] = []
    windows: list[WindowResult] = []
    fit: FitSettings = FitSettings()

    model_config = ConfigDict(
        extra="forbid", frozen=True, validate_by_name=True, validate_by_alias=True, serialize_by_alias=True
    )

    @model_validator(mode="after")
    def _ordered(self) -> Report:
        if self.ejections != sorted(set(self.ejections)):
            raise ValueError("ejections must be strictly increasing frame indices")
        if [w.index for w in self.windows] != list(range(len(self.windows))):
            raise ValueError("windows must be indexed 0, 1, 2, ... in order")
        return self

    def to_json(self) -> str:
        """Plain JSON (no NaN, no Infinity: ``allow_nan=False`` would refuse them), keys as in cli.md."""
        return json.dumps(self.model_dump(mode="json"), allow_nan=False, indent=2)

    def write(self, path: str | Path) -> Path:
        path = Path(path)
        try:
            path.write_text(self.to_json() + "\n")
        except OSError as exc:
            raise MeniscopeError(path, f"cannot write the report: {exc.strerror or exc}") from None
        return path

    @classmethod
    def load(cls, path: str | Path) -> Report:
        """Read and validate a report; any problem is one MeniscopeError naming the file."""
        try:
            return cls.model_validate_json(Path(path).read_bytes())
        except OSError as exc:
            raise MeniscopeError(path, f"cannot read the report: {exc.strerror or exc}") from None
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first["loc"]) or "report"
            raise MeniscopeError(path, f"not a {SCHEMA} report: {where}: {first['msg']}") from None
