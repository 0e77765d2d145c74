"""The refinement lane of ``meniscope serve --refine``: closed windows refined by synthesis off the frame path.

A window's refinement (:func:`service.analysis.offline.refine_window`, the very function ``meniscope analyze
--refine`` runs) costs tens of seconds of CPU, thousands of times the 10 ms between windows; the fast result of
every window is published as before, and the lane publishes a refined update of the same window later. Its
policy (docs/service.md): one window waits at most, the newest closed one; a window that closes while another
waits replaces it, and the one replaced is skipped and counted: an operator wants the latest state, and no
backlog of stale windows can grow. The work runs in a process of its own at the lowest CPU priority
(:data:`LANE_NICE`, and Linux's idle scheduling class), so that the frames and the fast fits get the CPU first.

The pipeline keeps references to the last :data:`KEEP_WINDOWS` windows' worth of ROI frames (:class:`RecentFrames`,
no copies) and hands a closed window over with references to its frames; only the window the lane takes has its
frames gathered into one array, on the lane's own thread.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Generic, TypeVar

import numpy as np

from service.analysis.results import FitSettings, WindowResult
from service.analysis.segment import Window
from service.sources import FrameBatch

log = logging.getLogger(__name__)

#: Niceness of the lane's process by default (the setting ``refine_nice``): the lowest priority there is, below the
#: fits' and the web side's.
LANE_NICE = 19
#: Frames kept for the lane, in windows of ``max_window_s``: a window is handed over as it closes, a few frames after
#: its end, so two windows' worth covers it with room for the look-ahead.
KEEP_WINDOWS = 2

_T = TypeVar("_T")


class NewestSlot(Generic[_T]):
    """A slot of one item: :meth:`offer` puts an item there (replacing the one waiting, which it returns: skipped),
    :meth:`take` waits for it and empties the slot. What a worker thousands of times slower than the offers takes
    is always the newest."""

    def __init__(self) -> None:
        self._item: _T | None = None
        self._closed = False
        self._changed = threading.Condition()

    def offer(self, item: _T) -> _T | None:
        """Put ``item`` in the slot; the item it replaced, if one waited."""
        with self._changed:
            replaced, self._item = self._item, item
            self._changed.notify()
        return replaced

    def take(self, timeout: float | None = None) -> _T | None:
        """The waiting item (the slot emptied), waiting for one up to ``timeout`` s; None when none came or the
        slot is closed."""
        with self._changed:
            self._changed.wait_for(lambda: self._item is not None or self._closed, timeout)
            item, self._item = self._item, None
        return None if self._closed else item

    def close(self) -> _T | None:
        """Wake :meth:`take` for good; the item still waiting, if any (never taken)."""
        with self._changed:
            self._closed, item, self._item = True, self._item, None
            self._changed.notify_all()
        return item


class RecentFrames:
    """References to the ROI frames of the last reads, at least ``keep`` frames (no copies: a read's pixels stay
    alive while referenced)."""

    def __init__(self, keep: int) -> None:
        self.keep = keep
        self._reads: deque[FrameBatch] = deque()
        self._frames = 0

    def add(self, reads: tuple[FrameBatch, ...]) -> None:
        for read in reads:
            self._reads.append(read)
            self._frames += len(read)
        while self._frames - len(self._reads[0]) >= self.keep:
            self._frames -= len(self._reads.popleft())

    def covering(self, start: int, end: int) -> tuple[FrameBatch, ...]:
        """The reads holding any frame with index in [start, end)."""
        return tuple(r for r in self._reads if len(r) and r.indices[0] < end and r.indices[-1] >= start)


def gather(reads: tuple[FrameBatch, ...], start: int, end: int) -> np.ndarray | None:
    """The frames with indices start..end-1 from ``reads``, (end - start, H, W) as stored; None where any is
    missing (dropped, or lost upstream)."""
    if not reads:
        return None
    out = np.empty((end - start, *reads[0].pixels.shape[1:]), reads[0].pixels.dtype)
    seen = np.zeros(end - start, bool)
    for read in reads:
        inside = (read.indices >= start) & (read.indices < end)
        out[read.indices[inside] - start] = read.pixels[inside]
        seen[read.indices[inside] - start] = True
    return out if seen.all() else None


@dataclass(frozen=True)
class Offered:
    """A closed window handed to the lane: the pipeline run it came from, the window, its frames' records, references
    to the reads holding its frames, its frame rate, and when (monotonic s) the frame that closed it was read."""

    run: int
    window: Window
    records: np.ndarray
    reads: tuple[FrameBatch, ...]
    fps: float
    closed_at: float


@dataclass(frozen=True)
class RefinedUpdate:
    """A window's refined result, for the publishers to send as an update of that window: the run and window it
    belongs to (:attr:`Offered.run`, the window's index), the method that made it (``network+synthesis``), the
    source's name, the refined series (mm per frame), and when (monotonic s) its closing frame was read, the lane took
    it, its process started and finished it."""

    run: int
    result: WindowResult
    method: str
    source: str
    values: np.ndarray
    fps: float
    closed_at: float
    taken_at: float
    started_at: float
    finished_at: float


@dataclass(frozen=True)
class LaneConfig:
    """What the lane's process needs: the scene file, the model folder, the per-frame method and the window fit's
    settings of the service (``fit``)."""

    scene: Path
    models: Path
    method: str
    fit: FitSettings


def idle_priority(nice: int) -> None:
    """Lower this process to ``nice`` and, at the lowest niceness (19), to Linux's idle class: a nice-19 process
    still takes about a tenth of a core from saturated ones (weight 15 against the fits' 110-335); an idle-class one
    runs only where no other wants the core, and every thread it starts afterwards inherits the class."""
    os.nice(nice)
    if nice >= LANE_NICE and hasattr(os, "SCHED_IDLE"):
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))


def _serve(conn: Connection, config: LaneConfig, nice: int) -> None:
    """The lane's process: refine each (window, records, frames, fps) the pipe brings until None, answering each
    with (result, series, started, finished), or (the reason,) where the refinement was rejected (the fit workers
    already published that window as the default method reports it), or, where it raised, the error as text."""
    idle_priority(nice)
    from service.analysis.offline import RefinedWindow, refine_window, refined_settings, start_settings
    from service.pipeline.windows import fit_or_failed, job_for, window_model_for
    from service.scene import Scene

    scene, first = Scene.load(config.scene), start_settings(config.fit)
    refined = refined_settings(first)
    model = window_model_for(first, config.models, config.method)
    fitted_first = config.method == "network"  # as analyze: the network's windows are searched from their fit
    conn.send("ready")
    try:
        while (sent := conn.recv()) is not None:
            window, records, frames, fps = sent
            started = time.monotonic()
            try:
                start, unrefined = None, None
                if fitted_first:  # the search's start, and the window as the fit workers fitted it
                    job = job_for(window, records, scene.nozzle.radius_mm, first.transient_frames(fps), model=model)
                    start = fit_or_failed(job, fps, first)
                    unrefined = RefinedWindow.unrefined(job, records, fit_or_failed(job, fps, config.fit))
                out = refine_window(scene, window, records, frames, fps, refined, start, unrefined=unrefined)
                answer: tuple | str = (
                    (out.rejected,) if out.rejected else (out.result, out.series, started, time.monotonic())
                )
            except Exception as exc:
                answer = f"{type(exc).__name__}: {exc}"
            conn.send(answer)
    except (EOFError, OSError):  # the service went away
        return


class RefineLane:
    """One process at ``nice`` (added to this process's niceness) refining the newest closed window offered
    (:meth:`offer`), each result to ``on_refined``; each window skipped (replaced while it waited, its frames
    incomplete, its refinement rejected or failed: logged) to ``on_skipped``."""

    def __init__(
        self,
        config: LaneConfig,
        on_refined: Callable[[RefinedUpdate], None],
        on_skipped: Callable[[str], None],
        nice: int = LANE_NICE,
    ) -> None:
        from service.analysis.offline import method_label, refined_from

        self.config, self.on_refined, self.on_skipped, self.nice = config, on_refined, on_skipped, nice
        self._refinable = refined_from
        self.method = method_label(config.method, True)
        self._slot: NewestSlot[tuple[Offered, str]] = NewestSlot()
        context = multiprocessing.get_context("spawn")  # no threads or locks inherited
        self._conn, child = context.Pipe()
        self.process = context.Process(target=_serve, args=(child, config, nice), name="meniscope-refine", daemon=True)
        self.process.start()
        child.close()
        self._thread = threading.Thread(target=self._run, name="meniscope-refine", daemon=True)
        self._thread.start()

    def wants(self, window: Window, fps: float) -> bool:
        """Whether ``window`` is long enough to refine."""
        return self._refinable(window, fps, self.config.fit) is not None

    def offer(self, offered: Offered, source: str) -> None:
        """Hand a closed window over (returns at once); the window waiting before it, if any, is skipped. A window
        with frames missing (NaN records: dropped, or lost upstream) is skipped at once and replaces nothing."""
        if np.isnan(offered.records["brightness"]).any():
            self.on_skipped("incomplete")
        elif self._slot.offer((offered, source)) is not None:
            self.on_skipped("replaced")

    def close(self, timeout: float = 5.0) -> None:
        """Stop: the window waiting is dropped (skipped), the one in the process abandoned, the process ended."""
        if self._slot.close() is not None:
            self.on_skipped("replaced")
        try:
            self._conn.send(None)
        except OSError:
            pass
        self.process.join(timeout)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(timeout)
        self._thread.join(timeout)

    def _run(self) -> None:
        """Take the newest window, gather its frames, refine it in the process, hand the result on; until closed."""
        try:
            if self._conn.recv() != "ready":
                return
            while (item := self._slot.take()) is not None:
                offered, source = item
                taken_at = time.monotonic()
                w = offered.window
                frames = gather(offered.reads, w.start, w.end)
                if frames is None:
                    self.on_skipped("incomplete")
                    continue
                self._conn.send((w, offered.records, frames, offered.fps))
                answer = self._conn.recv()
                if isinstance(answer, str):
                    log.warning("refining window %d (frames %d-%d) failed: %s", w.index, w.start, w.end, answer)
                    self.on_skipped("failed")
                    continue
                if len(answer) == 1:
                    log.info("window %d (frames %d-%d) not refined: %s", w.index, w.start, w.end, answer[0])
                    self.on_skipped("rejected")
                    continue
                result, series, started, finished = answer
                self.on_refined(
                    RefinedUpdate(
                        offered.run,
                        result,
                        self.method,
                        source,
                        series,
                        offered.fps,
                        offered.closed_at,
                        taken_at,
                        started,
                        finished,
                    )
                )
        except (EOFError, OSError):  # the process died or was stopped
            return
