"""One running service: settings, pipeline supervisor, publishers, history, metrics, WebSocket hub.

Built by :func:`service.server.app.create_app`, started and stopped by the app's lifespan, reached
by the routes as ``request.app.state.service``.
"""
from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field

from service.pipeline.runtime import PipelineStats
from service.pipeline.supervisor import Health, Supervisor
from service.scene import Scene
from service.server.frames import FrameViews
from service.server.history import History
from service.server.hub import Hub
from service.server.metrics import HistoryHealth, Metrics
from service.server.publishers import Publishers
from service.server.trigger_zmq import TriggerSubscriber
from service.server.zmq_publisher import ZmqPublisher
from service.settings import ServiceSettings

#: The history database, in the data folder.
HISTORY_FILE = "history.sqlite"


@dataclass
class Service:
    """Everything the routes reach through ``request.app.state.service``."""

    settings: ServiceSettings
    stats: PipelineStats = field(default_factory=PipelineStats)
    started: float = field(default_factory=time.time)
    supervisor: Supervisor | None = None
    publishers: Publishers | None = None
    history: History | None = None
    metrics: Metrics | None = None
    hub: Hub | None = None
    zmq: ZmqPublisher | None = None
    views: FrameViews | None = None
    trigger: TriggerSubscriber | None = None

    def websocket_counts(self) -> tuple[int, int]:
        return (self.hub.clients, self.hub.skipped) if self.hub is not None else (0, 0)

    def frame_views(self) -> FrameViews:
        """The dashboard's pictures for the current scene (made on first use; the scene may be bad)."""
        if self.views is None or self.views.scene_path != self.settings.scene:
            self.views = FrameViews(Scene.load(self.settings.scene), self.settings.scene)
        return self.views

    def health(self) -> Health:
        """The pipeline's health, degraded while the history cannot be written."""
        if self.supervisor is None:
            return Health("starting", "the service is starting", self.started, 0)
        health = self.supervisor.health()
        error = self.publishers.history_error if self.publishers is not None else None
        return health if error is None else health.degraded(error)

    def history_health(self) -> HistoryHealth:
        p = self.publishers
        if p is None:
            return HistoryHealth()
        return HistoryHealth(p.history_error, p.history_failures, p.backlog, p.history_lost)

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        s = self.settings
        self.history = History(s.data_dir / HISTORY_FILE, s.retention_days, s.retention_windows)
        self.zmq = ZmqPublisher(s.zmq_publish) if s.zmq_publish else None
        self.hub = Hub(loop, s.client_queue)
        self.metrics = Metrics(self.stats, self.health, self.websocket_counts, self.history_health)
        self.publishers = Publishers(self.history, self.metrics, self.zmq, self.hub).start()
        self.supervisor = Supervisor(s, self.publishers, self.stats).start()
        self.trigger = TriggerSubscriber(s.trigger_zmq, self.stats.trigger) if s.trigger_zmq else None

    def stop(self) -> None:
        """In order: the trigger and the pipeline stop, the publishers drain and close ZeroMQ, the history closes."""
        if self.trigger is not None:
            self.trigger.close()
        if self.supervisor is not None:
            self.supervisor.stop()
        if self.publishers is not None:
            self.publishers.stop()
        elif self.zmq is not None:
            self.zmq.close()
        if self.history is not None:
            self.history.close()

    def reconfigure(self, settings: ServiceSettings) -> None:
        self.settings = settings
        if self.supervisor is not None:
            self.supervisor.reconfigure(settings)
