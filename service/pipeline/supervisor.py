"""Keeps the pipeline running: opens the model and the source, restarts after failures, swaps settings.

A missing or corrupt model, an unreadable source or a camera that disappears is a
:class:`MeniscopeError`; the supervisor reports it as the reason it is not ready and tries again
after 1, 2, 4, ... s (at most ``retry_max_s``), so the service keeps answering and recovers by itself
once the cause is gone. A replay without loop that ends leaves it not ready until the settings change;
any other source that ends its stream is reconnected like one that failed.

Ready means frames flow and carry a picture: a running source that has delivered nothing for
:data:`SOURCE_SILENT_S` (a ZeroMQ sender that died) is ``stalled``, and one whose latest frame is flat
(a dark or capped camera, a saturated sensor: its ROI spans under :data:`FLAT_FRACTION` of full scale)
is ``no_signal``, and one that shows no highlight (its brightest pixel under
:data:`~service.pipeline.records.NO_HIGHLIGHT` of full scale above its mean: nothing of the meniscus is seen)
is ``no_highlight``; these are not ready, and ready again as soon as that changes.
"""

from __future__ import annotations

import gc
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Literal
from urllib.parse import urlsplit

from service.errors import MeniscopeError
from service.inverse.methods import open_method
from service.pipeline.demo import demo_uri
from service.pipeline.fitting import FitPool
from service.pipeline.records import NO_HIGHLIGHT
from service.pipeline.refining import LaneConfig, RefineLane
from service.pipeline.runtime import Pipeline, PipelineSink, PipelineStats
from service.pipeline.trigger import TriggerInbox
from service.scene import Scene
from service.server.settings import ServiceSettings, resolve_source
from service.sources import FrameSource, open_source

log = logging.getLogger(__name__)

State = Literal[
    "starting", "running", "stalled", "no_signal", "no_highlight", "degraded", "retrying", "ended", "stopped"
]
#: A running source that has sent nothing for this long (s) is stalled (or 4 frame periods of a slow one).
SOURCE_SILENT_S = 2.0
#: A frame whose ROI pixels span less than this fraction of full scale shows nothing (dark, capped, saturated).
FLAT_FRACTION = 0.02


@dataclass(frozen=True)
class Health:
    """What /readyz and /api/v1/status say: ready only while frames flow through a loaded model."""

    state: State
    reason: str | None
    since: float  # wall-clock time (s since the epoch) of the last change
    attempts: int  # failed attempts in a row
    source: dict[str, Any] = field(default_factory=dict)

    @property
    def ready(self) -> bool:
        return self.state == "running"

    def degraded(self, reason: str) -> Health:
        """This health, not ready because of ``reason`` (the history cannot be written)."""
        return (
            Health(
                "degraded",
                reason if self.reason is None else f"{self.reason}; {reason}",
                self.since,
                self.attempts,
                self.source,
            )
            if self.ready
            else self
        )


class Supervisor:
    """Runs :class:`Pipeline` for the current settings in a thread of its own until :meth:`stop`; ``trigger``: the
    printer's ejection events, which every pipeline it runs reads (with the setting ``trigger = "printer"``)."""

    def __init__(
        self,
        settings: ServiceSettings,
        sink: PipelineSink,
        stats: PipelineStats | None = None,
        trigger: TriggerInbox | None = None,
    ) -> None:
        self.settings, self.sink = settings, sink
        self.stats = stats or PipelineStats()
        self.trigger = trigger
        self._health = Health("starting", None, time.time(), 0)
        self._source: FrameSource | None = None
        self._fits: FitPool | None = None
        self._lane: RefineLane | None = None
        self._attempts = 0  # failed attempts in a row
        self._running_at = 0.0  # monotonic time (s) the current run started
        self._wake = threading.Event()  # interrupts a wait between attempts
        self._run_stop = threading.Event()  # stops the pipeline now running
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="meniscope-supervisor", daemon=True)

    def start(self) -> Supervisor:
        self._thread.start()
        return self

    def stop(self, timeout: float = 10.0) -> None:
        self._closing.set()
        self._wake.set()
        self._run_stop.set()
        self._thread.join(timeout)

    def reconfigure(self, settings: ServiceSettings) -> None:
        """Switch to ``settings``: the running pipeline stops and one for the new settings starts."""
        self.settings = settings
        self._wake.set()
        self._run_stop.set()

    def health(self) -> Health:
        h, source = self._health, self._source
        state, reason = h.state, h.reason
        if state == "running" and source is not None:
            state, reason = self._flow(source)
        return Health(state, reason, h.since, h.attempts, source.describe() if source is not None else h.source)

    def _flow(self, source: FrameSource) -> tuple[State, str | None]:
        """What a running pipeline delivers now: frames with a picture, no frames, or flat frames."""
        silent_s = time.monotonic() - max(self.stats.last_frame_at, self._running_at)
        limit = max(SOURCE_SILENT_S, 4.0 / source.fps) if source.is_open else SOURCE_SILENT_S
        if silent_s > limit:
            return "stalled", f"no frames from {source.uri} for {silent_s:.1f} s"
        latest = self.stats.latest
        if latest is not None and latest.pixels.size and source.is_open:
            span = int(latest.pixels.max()) - int(latest.pixels.min())
            full = 2**source.bit_depth - 1
            if span < FLAT_FRACTION * full:
                return "no_signal", (
                    f"no signal: frame {latest.index} is flat (its pixels span {span} of {full}: a dark "
                    "or capped camera, or a saturated one)"
                )
            highlight = (float(latest.pixels.max()) - float(latest.pixels.mean())) / full
            if highlight < NO_HIGHLIGHT:
                return "no_highlight", (
                    f"no highlight: frame {latest.index}'s brightest pixel is {100 * highlight:.1f} %"
                    " of full scale above its mean (unlit, or the nozzle out of view)"
                )
        return "running", None

    def _fit_pool(self, settings: ServiceSettings) -> FitPool:
        """The fit workers for ``settings`` (started once, again only when the fit settings change)."""
        pool = self._fits
        wanted = (settings.fit_workers, settings.fit, settings.fit_nice)
        if pool is None or pool.broken or (pool.workers, pool.settings, pool.nice) != wanted:
            if pool is not None:
                pool.close()
            pool = self._fits = FitPool(*wanted)
        return pool

    def _refine_lane(self, settings: ServiceSettings) -> RefineLane | None:
        """The refinement lane for ``settings`` (None without ``refine``): kept while they ask for the same one."""
        wanted = LaneConfig(settings.scene, settings.models, settings.method, settings.fit) if settings.refine else None
        lane = self._lane
        if lane is not None and (
            wanted != lane.config or lane.nice != settings.refine_nice or not lane.process.is_alive()
        ):
            lane.close()
            lane = None
        if lane is None and wanted is not None:
            lane = RefineLane(wanted, self.sink.on_refined, self.sink.on_refine_skipped, settings.refine_nice)
        self._lane = lane
        return lane

    def _set(self, state: State, reason: str | None, settings: ServiceSettings) -> None:
        """Report ``state`` of the run with ``settings``: its source, not that of settings changed meanwhile."""
        self._health = Health(state, reason, time.time(), self._attempts, {"uri": settings.source})

    def _loop(self) -> None:
        while not self._closing.is_set():
            self._wake.clear()  # before reading the settings: a change from now on stops the next run
            self._run_stop.clear()
            settings = self.settings
            try:
                self._set("starting", "opening the model and the source", settings)
                ended = self._run_once(settings)
            except Exception as exc:
                if self._closing.is_set():
                    break  # stopped while opening (the fit workers it waited for end with the process): no error
                if not isinstance(exc, MeniscopeError):
                    log.exception("pipeline failed")
                self._attempts += 1
                delay = min(2.0 ** (self._attempts - 1), settings.retry_max_s)
                self._set("retrying", f"{exc} (attempt {self._attempts}; next in {delay:g} s)", settings)
                self._wake.wait(delay)
                continue
            if ended:
                self._set("ended", "the source ended its stream: change the source to go on", settings)
                self._wake.wait()
        self._set("stopped", "the service is stopping", self.settings)
        if self._fits is not None:  # drain: the fits in flight come back before the publishers close
            self._fits.close()
            self._fits.join(5.0)
        if self._lane is not None:  # a refinement in flight is abandoned: it would take seconds
            self._lane.close()

    def _run_once(self, settings: ServiceSettings) -> bool:
        """Open everything, run until stopped or ended; True when the stream ended by itself."""
        scene = Scene.load(settings.scene)
        method, _ = open_method(
            settings.method,
            scene,
            settings.models,
            settings.nearest_database,
            threads=settings.threads,
            batch=settings.batch,
        )
        fits = self._fit_pool(settings)  # before the source opens: a replay's clock starts when it does
        lane = self._refine_lane(settings)
        uri = (
            demo_uri(settings.data_dir)
            if settings.source is None
            else resolve_source(settings.source, settings.recordings_folder)
        )
        scene_of_sim = {"scene": settings.scene} if urlsplit(uri).scheme.lower() == "sim" else {}
        with open_source(uri, **scene_of_sim) as source:  # a simulated camera renders the scene of the models
            pipeline = Pipeline(settings, scene, source, method, fits, self.sink, self.stats, self.trigger, lane)
            self._source, self._attempts = source, 0  # it ran: a later failure starts the backoff afresh
            self._running_at, self.stats.latest = time.monotonic(), None
            self._set("running", None, settings)
            # what is loaded by now (modules, model, app) lives as long as the service: out of the cyclic
            # collector's full passes, which scanned it all and stalled every thread for up to 93 ms
            gc.freeze()
            try:
                ended = pipeline.run(self._run_stop)
            finally:
                self._source = None
        if ended and source.kind != "replay":  # a camera or sender that stops may come back: reconnect
            raise MeniscopeError(uri, "the stream ended")
        return ended
