"""The web application: :func:`create_app` wires settings, pipeline, publishers and routes together.

An app factory rather than module-level singletons, so tests build one per case with a temporary
data folder. Starting the app (its lifespan) opens the history, binds ZeroMQ and starts the
pipeline's supervisor; the HTTP side answers from the first moment, ready or not.
"""
from __future__ import annotations

import asyncio
import time
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import AsyncIterator

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from service import __doc__ as package_doc
from service.pipeline.runtime import PipelineStats
from service.pipeline.supervisor import Health, Supervisor
from service.scene import Scene
from service.server import api, dashboard
from service.server.frames import FrameViews
from service.server.history import History
from service.server.hub import Hub
from service.server.metrics import Metrics
from service.server.publishers import Publishers
from service.server.static_files import STATIC
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

    def source_name(self) -> str:
        return self.settings.source or "demo"

    def websocket_counts(self) -> tuple[int, int]:
        return (self.hub.clients, self.hub.skipped) if self.hub is not None else (0, 0)

    def frame_views(self) -> FrameViews:
        """The dashboard's pictures for the current scene (made on first use; the scene may be bad)."""
        if self.views is None or self.views.scene_path != self.settings.scene:
            self.views = FrameViews(Scene.load(self.settings.scene), self.settings.scene)
        return self.views

    def health(self) -> Health:
        if self.supervisor is None:
            return Health("starting", "the service is starting", self.started, 0)
        return self.supervisor.health()

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        s = self.settings
        self.history = History(s.data_dir / HISTORY_FILE, s.retention_days, s.retention_windows)
        self.zmq = ZmqPublisher(s.zmq_publish) if s.zmq_publish else None
        self.hub = Hub(loop, s.client_queue)
        self.metrics = Metrics(self.stats, self.health, self.websocket_counts)
        self.publishers = Publishers(self.history, self.metrics, self.zmq, self.source_name, self.hub).start()
        self.supervisor = Supervisor(s, self.publishers, self.stats).start()

    def stop(self) -> None:
        if self.supervisor is not None:
            self.supervisor.stop()
        if self.publishers is not None:
            self.publishers.stop()
        if self.zmq is not None:
            self.zmq.close()
        if self.history is not None:
            self.history.close()

    def reconfigure(self, settings: ServiceSettings) -> None:
        self.settings = settings
        if self.supervisor is not None:
            self.supervisor.reconfigure(settings)


def create_app(settings: ServiceSettings) -> FastAPI:
    """The service for ``settings``; nothing starts until the app's lifespan does (uvicorn, TestClient)."""
    service = Service(settings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        service.start(asyncio.get_running_loop())
        try:
            yield
        finally:
            service.stop()

    app = FastAPI(title="meniscope", version="1", lifespan=lifespan,
                  description=(package_doc or "").splitlines()[0] + " Monitoring API (docs/service.md).")
    app.state.service = service
    app.include_router(api.router)
    app.include_router(dashboard.router)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    return app
