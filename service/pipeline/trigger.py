"""The printer's trigger as a live input: its ejection events, and the video detector checking them.

Events arrive from ZeroMQ (subscribed to in the pipeline process, where the segmenter runs) or HTTP (received by
the web process and sent on to the pipeline process over its pipe) as a frame index or as seconds since the stream's frame 0
(``time_s``, frame = round(time_s * fps), as in an ejection file), in any order and from any thread, into a
:class:`TriggerInbox`. With ``trigger = "printer"`` the segmenter cuts windows at them (as ``--ejections FILE``
does offline) and :class:`TriggerCheck` compares them with the video detector's ejections once both are known:
a printer ejection with no video ejection within ``tolerance`` frames, or a video ejection with no printer one,
is a disagreement (counted in :class:`TriggerCounts`, exported as ``meniscope_trigger_disagreements_total``).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

#: Most events waiting in the inbox; older ones are dropped beyond it (a printer firing with no pipeline).
INBOX_LIMIT = 100_000


@dataclass
class TriggerCounts:
    """The printer's ejections received and how they compared with the video's, since the service started."""

    received: int = 0
    agreed: int = 0
    printer_only: int = 0  # the printer fired, the video saw no ejection there
    video_only: int = 0  # the video saw an ejection the printer did not announce


def ejection_event(frame: int | None = None, time_s: float | None = None) -> tuple[str, float]:
    """One ejection event as (unit, value): exactly one of ``frame`` and ``time_s``, non-negative; ValueError
    otherwise. The inbox checks every event with it (the HTTP route's schema already admits only such events)."""
    if (frame is None) == (time_s is None):
        raise ValueError("an ejection event gives exactly one of frame and time_s")
    value = float(frame if frame is not None else time_s)  # type: ignore[arg-type]
    if not (np.isfinite(value) and value >= 0):
        raise ValueError(f"an ejection's frame or time must be a non-negative number, got {value!r}")
    return ("frame" if frame is not None else "time_s"), value


class TriggerInbox:
    """Printer ejection events as they arrive, thread-safe: each a frame index or seconds since frame 0."""

    def __init__(self, counts: TriggerCounts | None = None) -> None:
        self.counts = counts or TriggerCounts()
        self._lock = threading.Lock()
        self._events: list[tuple[str, float]] = []

    def add(self, frame: int | None = None, time_s: float | None = None) -> None:
        """One ejection, at ``frame`` or ``time_s`` (exactly one, non-negative); ValueError otherwise."""
        event = ejection_event(frame, time_s)
        with self._lock:
            self._events.append(event)
            del self._events[:-INBOX_LIMIT]
            self.counts.received += 1

    def take(self, fps: float) -> list[int]:
        """The events received since the last call, as frame indices at ``fps``."""
        with self._lock:
            events, self._events = self._events, []
        return [int(round(v * fps)) if unit == "time_s" else int(v) for unit, v in events]


class TriggerCheck:
    """The printer's ejections (from ``inbox``) as the cuts, checked against the video detector's."""

    def __init__(self, inbox: TriggerInbox, fps: float, wait_frames: int, tolerance: int = 2) -> None:
        self.inbox, self.fps, self.wait, self.tolerance = inbox, fps, max(0, wait_frames), tolerance
        self.printer: list[int] = []  # printer ejections not yet compared
        self._video: list[int] = []
        self.cuts: list[int] = []  # printer ejections not yet cut

    def update(self, video: list[int], newest: int, settled: int) -> int:
        """Take new events and the video's new ejections; compare those before both are final (the detector's
        ``settled``: it holds a stream's first ejections until it knows their period); return the frame before
        which the cuts are known (``wait_frames`` behind ``newest``)."""
        fresh = self.inbox.take(self.fps)
        self.printer = sorted(self.printer + fresh)
        self.cuts = sorted(set(self.cuts + fresh))
        self._video += video
        until = newest + 1 - self.wait
        self._compare(min(until, settled) - self.tolerance)
        return until

    def _compare(self, before: int) -> None:
        """Match the printer's ejections before frame ``before`` with the video's (each at most once, within
        tolerance; the video's are known up to ``before + tolerance``); count those left unmatched."""
        printer = np.asarray([p for p in self.printer if p < before], np.int64)
        video = np.asarray(self._video, np.int64)
        video = video[video < before + self.tolerance]
        used = np.zeros(video.size, bool)
        for p in printer:
            near = np.flatnonzero(~used & (np.abs(video - p) <= self.tolerance))
            if near.size:
                used[near[np.argmin(np.abs(video[near] - p))]] = True
        c = self.inbox.counts
        c.agreed += int(used.sum())
        c.printer_only += printer.size - int(used.sum())
        c.video_only += int((~used & (video < before)).sum())
        self.printer = [p for p in self.printer if p >= before]
        gone = set(video[used | (video < before)].tolist())
        self._video = [v for v in self._video if v not in gone]
