"""The lab frames a calibration looks at: a handful fitted one by one, and a larger stack for static statistics."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.analysis.results import FitSettings
from service.analysis.segment import find_ejections, frame_activity, frame_steps, windows_between
from service.calibration import LOOKED, WINDOWS
from service.errors import MeniscopeError
from service.inverse.synthesis import MIN_FRAMES
from service.recordings import open_recording

#: Every this many frames of a window are fitted: at 19,000 frames/s mode 2 (~3.5 kHz) stays below the Nyquist
#: frequency, and a search costs half.
STRIDE = 2


@dataclass(frozen=True)
class LabWindow:
    """The frames a window shows after its ejection's transient: ``frames`` (m, H, W) whole recorded frames as stored
    (their dtype too: a large camera's frames stay small), their numbers ``indices`` (m,), and ``t`` (m,) s since the
    window's ejection."""

    index: int
    indices: np.ndarray
    frames: np.ndarray
    t: np.ndarray

    def as_dict(self) -> dict:
        """Which frames were fitted, for the report."""
        return {
            "window": self.index,
            "first": int(self.indices[0]),
            "last": int(self.indices[-1]),
            "stride": int(self.indices[1] - self.indices[0]),
        }


def read_windows(
    rec, cuts: np.ndarray, count: int = WINDOWS, stride: int = STRIDE, looked: int = LOOKED
) -> tuple[LabWindow, ...]:
    """Up to ``count`` windows between the ejections ``cuts`` of an open recording: of up to ``looked`` windows spread
    over it that begin and end at an ejection and hold enough frames after the transient for the search
    (:data:`~service.inverse.synthesis.MIN_FRAMES` at ``stride``), those whose frames vary most (a settled window says little)."""
    fps = rec.fps
    skip = FitSettings().transient_frames(fps)
    whole = [
        w
        for w in windows_between(cuts, len(rec))
        if w.starts_at_ejection and w.ends_at_ejection and w.end - w.oscillation_start(skip) >= MIN_FRAMES * stride
    ]
    picked = [whole[i] for i in np.unique(np.linspace(0, len(whole) - 1, min(looked, len(whole))).round().astype(int))]
    kept: list[tuple[float, LabWindow]] = []  # the most varying so far: at most ``count`` windows held at once
    for w in picked:
        indices = np.arange(w.oscillation_start(skip), w.end, stride)
        frames = np.stack([rec[int(i)] for i in indices])
        kept.append((float(frames.std(axis=0).mean()), LabWindow(w.index, indices, frames, (indices - w.start) / fps)))
        kept = sorted(kept, key=lambda pair: -pair[0])[:count]
    return tuple(sorted((window for _, window in kept), key=lambda window: window.index))


@dataclass(frozen=True)
class Footage:
    """Frames as fractions of full scale (float32, whole recorded frame).

    ``frames`` (K, H, W): the frames whose motion is fitted, ``indices`` (K,) their frame numbers;
    ``stack`` (S, H, W): frames spread over the whole recording, for the temporal median (static scene,
    ROI search) and the temporal variance of static pixels (noise model); ``windows`` (K,) the window between
    ejections each fitted frame lies in (the printer's ejections, its rate's, or the video's, as ``analyze`` finds them);
    ``lab_windows`` whole windows, for the stage that holds their frames to Eq. 1 (:mod:`.windows`).
    """

    path: Path
    frames: np.ndarray
    indices: np.ndarray
    stack: np.ndarray
    bit_depth: int
    fps: float
    windows: np.ndarray
    lab_windows: tuple[LabWindow, ...] = ()

    @property
    def full_scale(self) -> float:
        """The largest stored value, 2**bit_depth - 1."""
        return float(2**self.bit_depth - 1)


def spread(count: int, total: int) -> np.ndarray:
    """Up to ``count`` distinct frame numbers in ``0 .. total - 1``, sorted, on a golden-ratio stride, so that
    they fall in many phases of any periodic motion (an even stride can alias with the ejection period)."""
    golden = (np.sqrt(5.0) - 1.0) / 2.0
    return np.unique(np.floor(((np.arange(min(count, total)) + 0.5) * golden) % 1.0 * total).astype(np.int64))


def read_footage(
    path: str | Path,
    frames: int,
    stack: int = 120,
    ejections_file: str | Path | None = None,
    ejection_hz: float | None = None,
    lab_windows: int = WINDOWS,
) -> Footage:
    """Read ``frames`` frames to fit and a ``stack`` for statistics from a recording (any format we read), and up to
    ``lab_windows`` whole windows (:func:`read_windows`); the ejections from ``ejections_file``, at ``ejection_hz``,
    or detected (as ``analyze`` takes them)."""
    path = Path(path)
    with open_recording(path) as rec:
        total = len(rec)
        if total < 2:
            raise MeniscopeError(path, f"calibration needs at least 2 frames, the recording has {total}")
        top = float(2**rec.bit_depth - 1)
        read = lambda idx: np.stack([rec[int(i)] for i in idx]).astype(np.float32) / top
        indices = spread(frames, total)
        stack_idx = np.unique(np.linspace(0, total - 1, min(stack, total)).round().astype(np.int64))
        cuts = _ejections(path, rec, total, ejections_file, ejection_hz)
        windows = np.searchsorted(cuts, indices, side="right")
        whole = read_windows(rec, cuts, lab_windows) if lab_windows else ()
        return Footage(path, read(indices), indices, read(stack_idx), rec.bit_depth, rec.fps, windows, whole)


def _ejections(
    path: Path, rec, total: int, ejections_file: str | Path | None, ejection_hz: float | None, chunk: int = 256
) -> np.ndarray:
    """Ejection frames of an open recording: read from the printer's file, placed at its rate on the frame-to-frame
    change, or, with neither, found from the video by the detector ``analyze`` and ``serve`` run."""
    if ejections_file is None and ejection_hz is None:
        from service.pipeline.ejections import detect_ejections_streamed
        from service.pipeline.measures import recording_measures

        change, novelty = recording_measures(path, rec.fps)
        return detect_ejections_streamed(change, rec.fps, offline=True, novelty=novelty)
    steps, previous = [], None
    for lo in range(0, total, chunk):
        frames = np.stack([rec[i] for i in range(lo, min(lo + chunk, total))])
        steps.append(frame_steps(frames, previous))
        previous = frames[-1]
    return find_ejections(frame_activity(np.concatenate(steps)), rec.fps, ejections_file, ejection_hz)[0]
