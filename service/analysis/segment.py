"""Ejections and the windows between them: read from a file or placed at a known rate; frame measures.

Window i runs from an ejection (that frame included, t = 0) to the next one (excluded). Frames
before the first ejection form a leading partial window (``starts_at_ejection`` false) and frames
from the last ejection on a trailing one (``ends_at_ejection`` false); with no ejections the whole
series is one window with both false. Windows are never empty.

Ejection files (``--ejections FILE``): text, one ejection per line, ``#`` starts a comment. Either
bare whole numbers (frame indices), or CSV with a header row naming a column ``frame`` (frame
indices) or ``time_s`` (seconds since frame 0; frame = round(time_s * fps)). Example::

    time_s
    0.0012
    0.0112
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike

from service.errors import MeniscopeError

#: 1 / Phi^-1(3/4): the median absolute deviation of Gaussian samples times this is their standard deviation.
MAD_TO_SIGMA = 1.482602218505602
_CHUNK_FRAMES = 256  # frame differences are taken this many frames at a time to bound memory


@dataclass(frozen=True)
class Window:
    """Frames [start, end) of a series, and whether each boundary is an ejection."""

    index: int
    start: int
    end: int  # exclusive
    starts_at_ejection: bool
    ends_at_ejection: bool

    def oscillation_start(self, transient: int) -> int:
        """First frame after the ejection's ``transient`` frames when the window starts at one, else its start."""
        return min(self.start + transient, self.end) if self.starts_at_ejection else self.start


def windows_between(ejections: ArrayLike, n_frames: int) -> list[Window]:
    """The windows of an ``n_frames`` series cut at ``ejections`` (frame indices, each in [0, n_frames))."""
    cuts = np.unique(np.asarray(ejections, dtype=np.int64))
    if cuts.size and (cuts[0] < 0 or cuts[-1] >= n_frames):
        raise ValueError(f"ejection frames must lie in [0, {n_frames}); got {cuts[0]}..{cuts[-1]}")
    bounds = np.unique(np.concatenate([[0], cuts, [n_frames]]))
    at_ejection = np.isin(bounds, cuts)
    return [
        Window(i, int(s), int(e), bool(a), bool(b))
        for i, (s, e, a, b) in enumerate(zip(bounds[:-1], bounds[1:], at_ejection[:-1], at_ejection[1:]))
    ]


def read_ejections(path: str | Path, fps: float, n_frames: int) -> np.ndarray:
    """Ejection frames from a file in the format of the module docstring; sorted, shape (E,), int64."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise MeniscopeError(path, f"cannot read the ejections: {getattr(exc, 'strerror', None) or exc}") from None
    rows = [(i, row) for i, row in enumerate(csv.reader(line.split("#")[0] for line in lines), start=1) if row]
    if not rows:
        raise MeniscopeError(path, "no ejections in the file")
    header = [cell.strip().lower() for cell in rows[0][1]]
    unit = next((h for h in ("frame", "time_s") if h in header), None)
    column = header.index(unit) if unit else 0
    if unit:
        rows = rows[1:]
    values = []
    for line, row in rows:
        cell = row[column].strip() if column < len(row) else ""
        try:
            value = float(cell)
        except ValueError:
            raise MeniscopeError(path, f"line {line}: {cell!r} is not a number (header 'frame' or 'time_s')") from None
        if not np.isfinite(value) or value < 0:
            raise MeniscopeError(path, f"line {line}: {cell!r} is not a non-negative number")
        if unit != "time_s" and value != int(value):
            raise MeniscopeError(
                path, f"line {line}: {cell!r} is not a whole frame index (times need a 'time_s' header)"
            )
        values.append(value)
    frames = np.round(np.asarray(values) * (fps if unit == "time_s" else 1.0)).astype(np.int64)
    if np.unique(frames).size != frames.size:
        raise MeniscopeError(path, "two ejections fall on the same frame")
    if frames.max() >= n_frames:
        raise MeniscopeError(path, f"ejection at frame {frames.max()} is beyond the series ({n_frames} frames)")
    return np.sort(frames)


def robust_sigma(values: np.ndarray) -> float:
    """1.4826 * MAD: the standard deviation of the Gaussian part of ``values`` (0 for none)."""
    return float(MAD_TO_SIGMA * np.median(np.abs(values - np.median(values)))) if values.size else 0.0


def robust_z(values: ArrayLike) -> np.ndarray:
    """(x - median) / (1.4826 MAD): a score that a few huge values do not shrink; shape as given."""
    x = np.nan_to_num(np.asarray(values, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    centre = np.median(x)
    spread = robust_sigma(x)
    if spread == 0:
        spread = np.mean(np.abs(x - centre)) or 1.0
    return (x - centre) / spread


def series_activity(series: ArrayLike) -> np.ndarray:
    """Per-frame activity of a displacement series: robust z-score of |x[n] - x[n-1]| (0 at n = 0 and at gaps)."""
    x = np.asarray(series, dtype=np.float64)
    step = np.abs(np.diff(x, prepend=x[:1]))
    return robust_z(np.where(np.isfinite(step), step, 0.0))


def frame_steps(frames: np.ndarray, previous: np.ndarray | None = None) -> np.ndarray:
    """Mean absolute difference of each frame from the one before: the video's raw activity.

    Parameters
    ----------
    frames : array of shape (N, H, W), any numeric dtype (memory-mapped is fine: read in chunks).
    previous : the frame before ``frames[0]`` (H, W), when streaming chunk by chunk; without it frame 0
        gets NaN (no predecessor).

    Returns
    -------
    ndarray of shape (N,), float64, in the frames' units.
    """
    n = frames.shape[0]
    step = np.full(n, np.nan)
    first = 0 if previous is not None else 1
    exact = frames.dtype in (np.uint8, np.uint16)  # OpenCV's absolute difference, summed in integers: exact
    for lo in range(first, n, _CHUNK_FRAMES):
        before = previous[None] if lo == 0 else frames[lo - 1 : lo]
        chunk = np.concatenate([before, frames[lo : lo + _CHUNK_FRAMES]])
        if exact:
            flat = chunk.reshape(len(chunk), -1)
            step[lo : lo + len(chunk) - 1] = (
                cv2.absdiff(flat[1:], flat[:-1]).sum(axis=1, dtype=_sum_type(flat)) / flat.shape[1]
            )
        else:
            diff = np.abs(np.diff(chunk.astype(np.float32), axis=0))
            step[lo : lo + len(chunk) - 1] = diff.mean(axis=(1, 2))
    return step


def frame_brightness(frames: np.ndarray) -> np.ndarray:
    """Mean pixel value of each frame (N, H, W) -> (N,), float64: the highlights the surface moves modulate
    it with the surface's own frequencies and decay rates (the window fit's poles, FitSettings.poles)."""
    flat = frames.reshape(len(frames), -1)
    if not np.issubdtype(flat.dtype, np.unsignedinteger):  # an unsigned sum of signed pixels would wrap
        return flat.mean(axis=1, dtype=np.float64)
    # an exact integer sum (2.7x faster than a float64 mean, and the same to the last bit: both are exact below 2**53)
    return flat.sum(axis=1, dtype=_sum_type(flat)) / flat.shape[1]


def _sum_type(flat: np.ndarray) -> type:
    """The integer type that sums a row of unsigned ``flat`` (N, P) exactly: 32 bits where no row can overflow
    them (faster), else 64."""
    return np.uint32 if flat.shape[1] * int(np.iinfo(flat.dtype).max) < 2**32 else np.uint64


def frame_activity(steps: ArrayLike) -> np.ndarray:
    """Robust z-score of :func:`frame_steps` (shape (N,)).

    Frame 0 has no predecessor: it gets frame 1's change, so that a recording that starts at an
    ejection has it at frame 0, not 1. Other NaN steps get the median (z = 0).
    """
    steps = np.array(steps, dtype=np.float64)
    if steps.size > 1 and not np.isfinite(steps[0]):
        steps[0] = steps[1]
    finite = np.isfinite(steps)
    return robust_z(np.where(finite, steps, np.median(steps[finite]) if finite.any() else 0.0))


def burst(activity: ArrayLike, frames: int) -> np.ndarray:
    """Forward box sum of the positive activity over ``frames`` frames, shape (N,): largest at a transient's start.

    An ejection moves the meniscus for a few frames (out and back, so the frame differences peak
    twice with a dip between); summed over the transient's length they make one peak, at its first frame.
    """
    z = np.clip(np.asarray(activity, dtype=np.float64), 0.0, None)
    frames = max(int(frames), 1)
    total = np.concatenate([[0.0], np.cumsum(z), np.full(frames - 1, np.sum(z))])
    return total[frames : frames + z.size] - total[: z.size]


def ejections_at_rate(activity: ArrayLike, fps: float, ejection_hz: float, transient_frames: int = 6) -> np.ndarray:
    """Ejections every fps / ejection_hz frames, in phase with the activity's strongest bursts.

    The activity and its :func:`burst` signal are folded modulo the period into round(period) phase
    bins; the ejection phase is the onset (:func:`_onset`) of the folded burst's largest bin, found in
    the folded activity. Returns sorted frame indices, shape (E,), int64.
    """
    z = np.asarray(activity, dtype=np.float64)
    period = fps / ejection_hz
    if not period >= 2:
        raise ValueError(f"an ejection rate of {ejection_hz} Hz is above half the frame rate ({fps} frames/s)")
    bins = max(int(round(min(period, z.size))), 1)
    phase_bin = np.minimum((np.mod(np.arange(z.size), period) / period * bins).astype(np.int64), bins - 1)
    counts = np.maximum(np.bincount(phase_bin, minlength=bins), 1)
    folded = np.bincount(phase_bin, weights=z, minlength=bins) / counts
    strongest = int(np.argmax(np.bincount(phase_bin, weights=burst(z, transient_frames), minlength=bins) / counts))
    back = min(transient_frames, bins - 1)  # the onset lies up to this many bins before, around the fold
    onset = _onset(np.roll(folded, back - strongest), back, transient_frames) - back + strongest
    phase = np.mod(onset, bins) * period / bins
    frames = np.round(phase + period * np.arange(int(np.ceil(z.size / period)) + 1)).astype(np.int64)
    return np.unique(frames[frames < z.size])


def _onset(activity: np.ndarray, peak: int, frames: int) -> int:
    """First frame in the ``frames`` before a burst peak whose activity reaches half their highest: the
    moment the droplet starts to leave, not when the oscillation it leaves behind adds the most."""
    lo = max(peak - frames, 0)
    span = activity[lo : peak + 1]
    return lo + int(np.argmax(span >= 0.5 * span.max()))


def find_ejections(
    activity: ArrayLike,
    fps: float,
    ejections_file: str | Path | None = None,
    ejection_hz: float | None = None,
    transient_frames: int = 6,
) -> tuple[np.ndarray, str]:
    """Ejection frames and how they were found: from the printer's file or at its known rate (found from the video
    otherwise, by :mod:`service.pipeline.ejections`, the detector of every front door).

    ``activity`` (N,) is the per-frame activity (:func:`frame_activity` or :func:`series_activity`);
    it places the phase of a known rate.
    """
    z = np.asarray(activity, dtype=np.float64)
    if ejections_file is not None:
        return read_ejections(ejections_file, fps, z.size), f"read from {Path(ejections_file).name}"
    if ejection_hz is not None:
        try:
            return ejections_at_rate(
                z, fps, ejection_hz, transient_frames
            ), f"every {fps / ejection_hz:.4g} frames, phase from the video"
        except ValueError as exc:
            raise MeniscopeError("--ejection-hz", str(exc)) from None
    raise ValueError("neither an ejection file nor a rate: the video's ejections are service.pipeline.ejections'")
