"""The live pipeline: the stages of :mod:`service.pipeline.stages` behind two threads and the fit pool.

source -> ROI -> per-frame measures, inverse's input -> bounded queue -> batched inference -> segmentation -> fits.
The acquisition thread reads the source, cuts each batch down to the scene's region of interest at once
(a sensor larger than the ROI costs no queue memory or copies beyond it), measures each frame's change,
mean brightness and novelty and makes the inverse method's input (a graph's pooled frames): work the
inference thread, the busier of the two, need not wait for; it offers the read to a queue of ``queue_batches`` reads;
when the queue is full the read is dropped and counted, so a camera is never made to wait and memory
never grows. The inference thread takes what is queued in one ONNX call, but no more frames than it
infers within ``batch_ms`` at the cost per frame measured so far (:class:`BatchBudget`; a read that
would pass the cap is split, its rest taken next), so a window's closing frame waits for at most one
short call before its own; then it cuts windows at ejections and hands closed windows to the
:class:`FitPool` at once. Results, the live trace and timings go to a :class:`PipelineSink`.
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from functools import partial
from typing import Protocol

import numpy as np

from service.analysis.results import WindowResult
from service.errors import MeniscopeError
from service.inverse.base import InverseMethod
from service.pipeline.ejections import EjectionDetector
from service.pipeline.fitting import FitPool
from service.pipeline.refining import KEEP_WINDOWS, Offered, RecentFrames, RefinedUpdate, RefineLane
from service.pipeline.segmenter import ClosedWindow, StreamingSegmenter
from service.pipeline.stages import FrameStages
from service.pipeline.trigger import TriggerCheck, TriggerCounts, TriggerInbox
from service.pipeline.windows import WindowJob, job_for, window_model_for
from service.scene import Scene
from service.server.settings import ServiceSettings
from service.sources import FrameBatch, FrameSource

log = logging.getLogger(__name__)

#: Seconds between two warnings that frames were dropped.
DROP_REPORT_S = 10.0
#: Numbers the pipeline runs of this process (a window is its run's and its index there).
_RUNS = itertools.count(1)


@dataclass(frozen=True)
class Acquired:
    """A read's ROI frames, when each was read (monotonic s), their records (N,) as acquisition measured them
    and the inverse method's input made of them (:meth:`FrameStages.measure`)."""

    batch: FrameBatch
    arrival: np.ndarray
    records: np.ndarray
    inputs: np.ndarray

    def __len__(self) -> int:
        return len(self.batch)

    def select(self, which: slice) -> Acquired:
        """The frames ``which`` picks, with what was measured and prepared of them."""
        return Acquired(self.batch.select(which), self.arrival[which], self.records[which], self.inputs[which])


@dataclass(frozen=True)
class Taken:
    """The frames of one inference call, from one or more reads: their indices, arrival times, records and the inverse
    method's input, in order, and the last frame's ROI pixels (the latest frame; no other pixels are joined: the
    input was prepared where they were read), and the reads themselves (references, for the refinement lane)."""

    indices: np.ndarray
    arrival: np.ndarray
    records: np.ndarray
    inputs: np.ndarray
    last_pixels: np.ndarray
    reads: tuple[FrameBatch, ...] = ()

    def __len__(self) -> int:
        return len(self.indices)

    @classmethod
    def of(cls, parts: list[Acquired]) -> Taken:
        """The frames of ``parts`` (at least one, none empty)."""
        joined = [
            getattr(parts[0], f) if len(parts) == 1 else np.concatenate([getattr(p, f) for p in parts])
            for f in ("arrival", "records", "inputs")
        ]
        indices = parts[0].batch.indices if len(parts) == 1 else np.concatenate([p.batch.indices for p in parts])
        return cls(indices, *joined, parts[-1].batch.pixels[-1], tuple(p.batch for p in parts))


@dataclass(frozen=True)
class FittedWindow:
    """A window's result with its samples (mm, NaN where missing), the name of the source its frames came
    from (:attr:`ServiceSettings.source_name`: a fit may come back after the settings changed), and when
    (monotonic s) the frame that closed it was read, the window went to the fit workers, a worker started
    and finished its fit (NaN if the fit raised) and its fit came back: where latency goes; the pipeline run it
    came from (a refined update finds its window by run and index) and the per-frame method."""

    result: WindowResult
    source: str
    values: np.ndarray
    fps: float
    closed_at: float
    dispatched_at: float
    fit_started_at: float
    fit_finished_at: float
    fitted_at: float
    run: int = 0
    method: str | None = None


@dataclass(frozen=True)
class TraceSnippet:
    """The latest ``values`` (mm, NaN where missing) at full frame rate from frame ``first_index``, and the
    ejections among them."""

    first_index: int
    fps: float
    values: np.ndarray
    ejections: list[int]


@dataclass(frozen=True)
class LatestFrame:
    """The last inferred frame: its ROI pixels as stored (H, W), coefficients d, p, a, b and D(0, t)."""

    index: int
    pixels: np.ndarray
    coefficients: tuple[float, float, float, float]
    centre_mm: float


class PipelineSink(Protocol):
    """Where the pipeline's output goes; every call must return at once (hand over, never wait)."""

    def on_window(self, fitted: FittedWindow) -> None: ...

    def on_trace(self, trace: TraceSnippet) -> None: ...

    def on_inference(self, seconds: float, frames: int) -> None: ...

    def on_refined(self, refined: RefinedUpdate) -> None: ...

    def on_refine_skipped(self, why: str) -> None: ...


@dataclass
class PipelineStats:
    """Counters since the service started (across source restarts) and the current rates (frames/s)."""

    frames_acquired: int = 0
    frames_inferred: int = 0
    frames_dropped: int = 0  # read, but no room in the queue
    frame_gaps: int = 0  # jumps in the source's frame indices
    frames_lost_upstream: int = 0  # frames inside those jumps
    windows_closed: int = 0
    windows_skipped: int = 0  # closed while every fit slot was busy
    fps_in: float = 0.0
    fps_out: float = 0.0
    last_frame_at: float = 0.0  # monotonic time (s) frames last arrived
    trigger: TriggerCounts = field(default_factory=TriggerCounts)  # the printer's ejections and the video's check
    latest: LatestFrame | None = field(default=None, repr=False)


class RateMeter:
    """Events per second, re-estimated once ``period`` s have passed."""

    def __init__(self, period: float = 1.0) -> None:
        self.period, self.rate = period, 0.0
        self._t0, self._count = time.monotonic(), 0

    def add(self, count: int, now: float) -> float:
        self._count += count
        if now - self._t0 >= self.period:
            self.rate = self._count / (now - self._t0)
            self._t0, self._count = now, 0
        return self.rate


class BatchBudget:
    """How many frames one inference call may take: as many as it infers within ``seconds`` at the cost per
    frame measured so far (an exponential average of recent calls), between 1 and ``most``; ``first`` before
    any call was measured. Bounded in time rather than frames because the cost per frame varies several
    times over with the method and with the machine's load."""

    def __init__(self, seconds: float, most: int, first: int, smoothing: float = 0.2) -> None:
        self.seconds, self.most, self.smoothing = seconds, most, smoothing
        self._first = max(1, min(first, most))
        self._cost: float | None = None  # seconds per frame

    def frames(self) -> int:
        """The cap for the next call."""
        if self._cost is None:
            return self._first
        return max(1, min(self.most, int(self.seconds / self._cost)))

    def record(self, seconds: float, frames: int) -> None:
        """Count a call that inferred ``frames`` in ``seconds``."""
        cost = seconds / max(frames, 1)
        self._cost = cost if self._cost is None else self._cost + self.smoothing * (cost - self._cost)


def segmenter_for(settings: ServiceSettings, fps: float, trigger: TriggerInbox | None = None) -> StreamingSegmenter:
    """The live segmenter ``settings`` ask for at ``fps``: ejections from the detector with the live look-ahead, no
    two within half the expected period (its own refractory time when no rate is given), windows cut at
    ``max_window_s``; with ``trigger = "printer"``, cut at the ``trigger``'s events, which the detector checks."""
    refractory = int(0.5 * fps / settings.ejection_hz) if settings.ejection_hz else None
    detector = EjectionDetector(fps, ratio=settings.ejection_ratio, refractory=refractory)
    check = None
    if settings.trigger == "printer" and trigger is not None:
        check = TriggerCheck(trigger, fps, int(round(settings.trigger_wait_s * fps)))
    return StreamingSegmenter(int(settings.max_window_s * fps), detector, drop_leading=True, trigger=check)


class Pipeline:
    """One run of the pipeline over an open ``source`` with an inverse ``method``; :meth:`run` until it ends.

    The ``fits`` pool outlives the run: fits of its last windows may still arrive after it stopped. So does the
    refinement ``lane`` (``serve --refine``), which gets each closed window the fits took, with its frames.
    """

    def __init__(
        self,
        settings: ServiceSettings,
        scene: Scene,
        source: FrameSource,
        method: InverseMethod,
        fits: FitPool,
        sink: PipelineSink,
        stats: PipelineStats,
        trigger: TriggerInbox | None = None,
        lane: RefineLane | None = None,
    ) -> None:
        self.stages = FrameStages(scene, source.format, source.uri, method)
        self.settings, self.source, self.method, self.fits = settings, source, method, fits
        self.lane, self.run_id = lane, next(_RUNS)
        keep = KEEP_WINDOWS * int(settings.max_window_s * source.fps)
        self._recent = RecentFrames(keep) if lane is not None else None  # the frames the lane may need
        self.sink, self.stats = sink, stats
        fps = source.fps
        self.segmenter = segmenter_for(settings, fps, trigger)
        self._queue: queue.Queue[Acquired] = queue.Queue(settings.queue_batches)
        self._rest: Acquired | None = None  # a read's frames past the last call's cap
        self.budget = BatchBudget(settings.batch_ms / 1e3, settings.batch, settings.read_frames)
        self._trace, self._trace_first = np.empty(0), 0
        self._trace_next = 0.0
        self._acquired = threading.Event()  # set when acquisition stopped (end, error or stop)
        self._error: BaseException | None = None
        self._fps = fps
        self._radius, self._transient = scene.nozzle.radius_mm, settings.fit.transient_frames(fps)
        self._window_model = window_model_for(settings.fit, settings.models, settings.method)
        self._reported = (time.monotonic(), stats.frames_dropped, stats.windows_skipped)

    def run(self, stop: threading.Event) -> bool:
        """Acquire and infer until ``stop`` is set or the stream ends (then True); raises what made it fail."""
        done = threading.Event()
        reader = threading.Thread(target=self._acquire, args=(stop, done), name="meniscope-acquire", daemon=True)
        reader.start()
        ended = False
        try:
            ended = self._infer(stop)
            if ended:
                self._dispatch(self.segmenter.finish(time.monotonic()))
        finally:
            done.set()
            reader.join()
        if self._error is not None:
            raise self._error
        return ended

    def _acquire(self, stop: threading.Event, done: threading.Event) -> None:
        """Read the source, score every batch's ROI and offer it to the queue; a full queue drops the batch."""
        meter, stats = RateMeter(), self.stats
        lost = self.source.stats
        try:
            while not (stop.is_set() or done.is_set()):
                batch = self.source.read(self.settings.read_frames)
                now = time.monotonic()
                if batch is None:
                    break
                stats.fps_in = meter.add(len(batch), now)
                if not len(batch):
                    continue
                batch = self.stages.roi(batch)
                stats.frames_acquired += len(batch)
                stats.last_frame_at = now
                seen = self.source.stats
                stats.frame_gaps += seen.gaps - lost.gaps
                stats.frames_lost_upstream += seen.dropped - lost.dropped
                lost = seen
                acquired = Acquired(batch, np.full(len(batch), now), *self.stages.measure(batch))
                try:
                    self._queue.put_nowait(acquired)
                except queue.Full:
                    stats.frames_dropped += len(batch)
        except MeniscopeError as exc:
            self._error = exc
        except Exception as exc:  # a camera library's own error: report it as the source's
            self._error = MeniscopeError(self.source.uri, f"the source failed: {type(exc).__name__}: {exc}")
        finally:
            self._acquired.set()

    def _infer(self, stop: threading.Event) -> bool:
        """The inference loop; True when the stream ended (everything read was processed)."""
        meter = RateMeter()
        while not stop.is_set():
            taken = self._take(self.budget.frames())
            if not taken:
                if self._acquired.is_set() and self._queue.empty():  # empty once acquisition stopped: all done
                    return self._error is None
                self.stats.fps_out = meter.add(0, time.monotonic())
                continue
            frames = Taken.of(taken)
            self._process(frames)
            self.stats.fps_out = meter.add(len(frames), time.monotonic())
            self._report_drops()
        return False

    def _take(self, most: int) -> list[Acquired]:
        """Reads for one call, ``most`` frames in all: the rest of a read split by the last call first, then
        queued ones, waiting (at most 0.05 s) only for the first; a read that would pass ``most`` is split and
        its rest kept. Empty when nothing came."""
        taken: list[Acquired] = []
        frames = 0
        while frames < most:
            if self._rest is not None:
                item, self._rest = self._rest, None
            else:
                try:
                    item = self._queue.get_nowait() if taken else self._queue.get(timeout=0.05)
                except queue.Empty:
                    break
            if frames + len(item) > most:
                cut = most - frames
                item, self._rest = item.select(slice(cut)), item.select(slice(cut, None))
            taken.append(item)
            frames += len(item)
        return taken

    def _report_drops(self) -> None:
        """Say so (a log warning, at most every ``DROP_REPORT_S``) when frames were dropped since the last time."""
        now, s = time.monotonic(), self.stats
        if now - self._reported[0] < DROP_REPORT_S:
            return
        dropped, skipped = s.frames_dropped - self._reported[1], s.windows_skipped - self._reported[2]
        if dropped or skipped:
            log.warning(
                "behind the source for the last %.0f s: %d frames dropped (%.0f frames/s in, %.0f inferred), "
                "%d windows left unfitted",
                now - self._reported[0],
                dropped,
                s.fps_in,
                s.fps_out,
                skipped,
            )
        self._reported = (now, s.frames_dropped, s.windows_skipped)

    def _process(self, taken: Taken) -> None:
        """Infer one call's frames, cut windows and hand them to the fits; update the trace and the latest frame."""
        indices = taken.indices
        t0 = time.perf_counter()
        records = self.stages.infer(taken.inputs, taken.records)
        seconds = time.perf_counter() - t0
        self.budget.record(seconds, len(taken))
        self.sink.on_inference(seconds, len(taken))
        self.stats.frames_inferred += len(taken)
        if self._recent is not None:
            self._recent.add(taken.reads)
        self._dispatch(
            self.segmenter.push(indices, records, records["change"], taken.arrival, novelty=records["novelty"])
        )
        last = records[-1]
        self.stats.latest = LatestFrame(
            int(indices[-1]),
            taken.last_pixels.copy(),
            (float(last["d"]), float(last["p"]), float(last["a"]), float(last["b"])),
            float(last["centre"]),
        )
        self._update_trace(indices, records["centre"])

    def _dispatch(self, closed: list[ClosedWindow]) -> None:
        """Each closed window's job (:func:`job_for`, as ``meniscope analyze`` makes it) to the fit workers."""
        for window in closed:
            job = job_for(
                window.window, window.values, self._radius, self._transient, window.closed_at, self._window_model
            )
            self.stats.windows_closed += 1
            dispatched_at = time.monotonic()
            if not self.fits.submit(job, self._fps, partial(self._fitted, dispatched_at)):
                self.stats.windows_skipped += 1
            elif self.lane is not None and self._recent is not None and self.lane.wants(window.window, self._fps):
                w = window.window
                reads = self._recent.covering(w.start, w.end)
                offered = Offered(self.run_id, w, window.values.copy(), reads, self._fps, window.closed_at)
                self.lane.offer(offered, self.settings.source_name)

    def _fitted(
        self, dispatched_at: float, job: WindowJob, result: WindowResult, started_at: float, finished_at: float
    ) -> None:
        self.sink.on_window(
            FittedWindow(
                result,
                self.settings.source_name,
                job.series,
                self._fps,
                job.closed_at,
                dispatched_at,
                started_at,
                finished_at,
                time.monotonic(),
                self.run_id,
                self.settings.method,
            )
        )

    def _update_trace(self, indices: np.ndarray, centre: np.ndarray) -> None:
        """Keep the last ``trace_frames`` samples; send them ``trace_hz`` times a second."""
        n = self.settings.trace_frames
        end = int(indices[-1]) + 1
        first, old_first = end - n, self._trace_first
        dense = np.full(n, np.nan)
        lo, hi = max(first, old_first), min(old_first + self._trace.size, end)
        if hi > lo:  # earlier samples still inside the span
            dense[lo - first : hi - first] = self._trace[lo - old_first : hi - old_first]
        keep = indices >= first
        dense[indices[keep] - first] = centre[keep]
        self._trace, self._trace_first = dense, first
        now = time.monotonic()
        if now >= self._trace_next:
            self._trace_next = now + 1.0 / self.settings.trace_hz
            ejections = [e for e in self.segmenter.ejections if e >= first]
            self.sink.on_trace(TraceSnippet(first, self.source.fps, dense.copy(), ejections))
