"""The web application: :func:`create_app` wires settings, pipeline, publishers and routes together.

An app factory rather than module-level singletons, so tests build one per case with a temporary
data folder. Starting the app (its lifespan) opens the history, binds ZeroMQ and starts the
pipeline's supervisor; the HTTP side answers from the first moment, ready or not.
"""
from __future__ import annotations

import asyncio
from contextlib import asynccontextmanager
from typing import AsyncIterator

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from service import __doc__ as package_doc
from service.server import api, dashboard
from service.server.components import Service
from service.server.static_files import STATIC
from service.settings import ServiceSettings


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
