"""Ejections and the windows between them: read from a file, placed at a known rate, or detected.

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

import numpy as np
from numpy.typing import ArrayLike
from scipy.signal import find_peaks

from service.errors import MeniscopeError

_MAD_TO_SIGMA = 1.482602218505602
_CHUNK_FRAMES = 256  # frame differences are taken this many frames at a time to bound memory


@dataclass(frozen=True)
class Window:
    """Frames [start, end) of a series, and whether each boundary is an ejection."""

    index: int
    start: int
    end: int  # exclusive
    starts_at_ejection: bool
    ends_at_ejection: bool


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
            raise MeniscopeError(path, f"line {line}: {cell!r} is not a whole frame index (times need a 'time_s' header)")
        values.append(value)
    frames = np.round(np.asarray(values) * (fps if unit == "time_s" else 1.0)).astype(np.int64)
    if np.unique(frames).size != frames.size:
        raise MeniscopeError(path, "two ejections fall on the same frame")
    if frames.max() >= n_frames:
        raise MeniscopeError(path, f"ejection at frame {frames.max()} is beyond the series ({n_frames} frames)")
    return np.sort(frames)


def robust_z(values: ArrayLike) -> np.ndarray:
    """(x - median) / (1.4826 MAD): a score that a few huge values do not shrink; shape as given."""
    x = np.nan_to_num(np.asarray(values, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    centre = np.median(x)
    spread = _MAD_TO_SIGMA * np.median(np.abs(x - centre))
    if spread == 0:
        spread = np.mean(np.abs(x - centre)) or 1.0
    return (x - centre) / spread


def series_activity(series: ArrayLike) -> np.ndarray:
    """Per-frame activity of a displacement series: robust z-score of |x[n] - x[n-1]| (0 at n = 0 and at gaps)."""
    x = np.asarray(series, dtype=np.float64)
    step = np.abs(np.diff(x, prepend=x[:1]))
    return robust_z(np.where(np.isfinite(step), step, 0.0))


def frame_activity(frames: np.ndarray) -> np.ndarray:
    """Per-frame activity of a video: robust z-score of the mean absolute difference from the previous frame.

    Parameters
    ----------
    frames : array of shape (N, H, W), any numeric dtype (memory-mapped is fine: read in chunks).

    Returns
    -------
    ndarray of shape (N,), float64; frame 0 (no predecessor) gets the median difference.
    """
    n = frames.shape[0]
    if n < 2:
        return np.zeros(n)
    step = np.empty(n)
    for lo in range(1, n, _CHUNK_FRAMES):
        chunk = np.asarray(frames[lo - 1 : lo + _CHUNK_FRAMES], dtype=np.float32)
        step[lo : lo + chunk.shape[0] - 1] = np.abs(np.diff(chunk, axis=0)).mean(axis=(1, 2))
    step[0] = np.median(step[1:])
    return robust_z(step)


def ejections_at_rate(activity: ArrayLike, fps: float, ejection_hz: float) -> np.ndarray:
    """Ejections every fps / ejection_hz frames, in phase with the activity's sharpest rise.

    The activity is folded modulo the period into round(period) phase bins; the ejection phase is
    the bin where the mean activity jumps most from the bin before (an ejection is an onset).
    Returns sorted frame indices, shape (E,), int64.
    """
    z = np.asarray(activity, dtype=np.float64)
    period = fps / ejection_hz
    if not period >= 2:
        raise ValueError(f"an ejection rate of {ejection_hz} Hz is above half the frame rate ({fps} frames/s)")
    bins = max(int(round(min(period, z.size))), 1)
    phase_bin = np.minimum((np.mod(np.arange(z.size), period) / period * bins).astype(np.int64), bins - 1)
    counts = np.bincount(phase_bin, minlength=bins)
    profile = np.bincount(phase_bin, weights=z, minlength=bins) / np.maximum(counts, 1)
    phase = np.argmax(profile - np.roll(profile, 1)) * period / bins
    frames = np.round(phase + period * np.arange(int(np.ceil(z.size / period)) + 1)).astype(np.int64)
    return np.unique(frames[frames < z.size])


def detect_ejections(
    activity: ArrayLike, fps: float, expected_hz: float | None = None, threshold: float = 8.0
) -> np.ndarray:
    """Ejection frames where the activity jumps above ``threshold`` robust sigmas.

    Each ejection is the first frame of an above-threshold run (the onset), keeping the strongest
    run when two are closer than half the expected period (2 ms when no rate is expected).
    Returns sorted frame indices, shape (E,), int64.
    """
    z = robust_z(activity)
    separation = 0.5 * fps / expected_hz if expected_hz else 2e-3 * fps
    peaks, _ = find_peaks(z, height=threshold, distance=max(1, int(separation)))
    above = np.concatenate([[False], z > threshold])
    onsets = np.flatnonzero(~above[:-1] & above[1:])  # first frame of each above-threshold run
    return np.unique(onsets[np.searchsorted(onsets, peaks, side="right") - 1])
