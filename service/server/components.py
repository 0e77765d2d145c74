"""One running service as the web process holds it: settings, the pipeline process, history reader, WebSocket hub.

Built by :func:`service.server.app.create_app`, started and stopped by the app's lifespan, reached by the
routes as ``request.app.state.service``. The frame path runs in the pipeline process
(:mod:`service.server.pipeline_process`); what the routes say of it comes from its latest report, and the
window history from SQLite.
"""

from __future__ import annotations

import asyncio
import os
import threading
import time
from dataclasses import dataclass, field

from prometheus_client import CollectorRegistry, generate_latest

from service.pipeline.runtime import LatestFrame, PipelineStats
from service.pipeline.supervisor import Health
from service.scene import Scene
from service.server.engine import HISTORY_FILE
from service.server.frames import FrameViews
from service.server.history import History
from service.server.hub import Hub
from service.server.metrics import HistoryHealth, status_registry
from service.server.pipeline_process import PipelineProcess
from service.server.settings import ServiceSettings


@dataclass
class Service:
    """Everything the routes reach through ``request.app.state.service``."""

    settings: ServiceSettings
    started: float = field(default_factory=time.time)
    pipeline: PipelineProcess | None = None
    history: History | None = None
    hub: Hub | None = None
    views: FrameViews | None = None
    registry: CollectorRegistry | None = None  # the pipeline's statistics and health, and the WebSocket counts
    ejections_sent: int = 0  # the printer's ejection events sent on to the pipeline process

    def eject(self, frame: int | None, time_s: float | None) -> bool:
        """Send one of the printer's ejection events on to the pipeline process; False when it is not running."""
        sent = self.pipeline is not None and self.pipeline.eject(frame, time_s)
        self.ejections_sent += sent
        return sent

    @property
    def stats(self) -> PipelineStats:
        report = self.pipeline.report if self.pipeline is not None else None
        return report.stats if report is not None else PipelineStats()

    @property
    def latest(self) -> LatestFrame | None:
        report = self.pipeline.report if self.pipeline is not None else None
        return report.latest if report is not None else None

    @property
    def unpublished(self) -> int:
        report = self.pipeline.report if self.pipeline is not None else None
        return report.unpublished if report is not None else 0

    @property
    def zmq_endpoint(self) -> str | None:
        return self.pipeline.endpoint if self.pipeline is not None else None

    def websocket_counts(self) -> tuple[int, int]:
        report = self.pipeline.report if self.pipeline is not None else None
        skipped = report.websocket_skipped if report is not None else 0
        return (self.hub.clients, self.hub.skipped + skipped) if self.hub is not None else (0, skipped)

    def frame_views(self) -> FrameViews:
        """The dashboard's pictures for the current scene (made on first use; the scene may be bad)."""
        if self.views is None or self.views.scene_path != self.settings.scene:
            self.views = FrameViews(Scene.load(self.settings.scene), self.settings.scene)
        return self.views

    def health(self) -> Health:
        """The pipeline's health (degraded while the history cannot be written), not ready while it is down."""
        if self.pipeline is None:
            return Health("starting", "the service is starting", self.started, 0)
        return self.pipeline.health()

    def history_health(self) -> HistoryHealth:
        report = self.pipeline.report if self.pipeline is not None else None
        return report.history if report is not None else HistoryHealth()

    def metrics(self) -> bytes:
        """Every metric, Prometheus text format: the web process's and the pipeline process's latest."""
        assert self.registry is not None
        report = self.pipeline.report if self.pipeline is not None else None
        return generate_latest(self.registry) + (report.metrics if report is not None else b"")

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        s = self.settings
        self.history = History(s.data_dir / HISTORY_FILE, s.retention_days, s.retention_windows)
        self.hub = Hub(loop, s.client_queue)
        self.registry = status_registry(lambda: self.stats, self.health, self.websocket_counts, self.history_health)
        self.pipeline = PipelineProcess(s, self.hub).start()
        # this thread (the event loop) and the request threads it starts from now on yield the CPU to the pipeline
        # process; the threads that restart it and read its pipe, started already, keep their priority
        os.setpriority(
            os.PRIO_PROCESS,
            threading.get_native_id(),
            min(19, os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) + s.web_nice),
        )

    def stop(self) -> None:
        """The pipeline process stops (in its order: pipeline, publishers and ZeroMQ, history), then the reader."""
        if self.pipeline is not None:
            self.pipeline.stop()
        if self.history is not None:
            self.history.close()

    def reconfigure(self, settings: ServiceSettings) -> None:
        self.settings = settings
        if self.pipeline is not None:
            self.pipeline.reconfigure(settings)
