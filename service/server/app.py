"""The web application: :func:`create_app` wires settings, pipeline, publishers and routes together.

An app factory rather than module-level singletons, so tests build one per case with a temporary
data folder. Starting the app (its lifespan) opens the history, binds ZeroMQ and starts the
pipeline's supervisor; the HTTP side answers from the first moment, ready or not. The API docs (/docs)
load Swagger UI from the package (swagger-ui-bundle), not a CDN: a PC beside a printer has no internet.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from swagger_ui_bundle import swagger_ui_path

from service import __doc__ as package_doc
from service.server import api, dashboard
from service.server.components import Service
from service.server.guard import Guard, default_hosts
from service.server.settings import ServiceSettings
from service.server.static_files import STATIC


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

    app = FastAPI(
        title="meniscope",
        version="1",
        lifespan=lifespan,
        docs_url=None,
        redoc_url=None,
        description=(package_doc or "").splitlines()[0] + " Monitoring API (docs/service.md).",
    )
    app.state.service = service
    app.include_router(api.router)
    app.include_router(dashboard.router)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    app.mount("/docs-assets", StaticFiles(directory=swagger_ui_path), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    def docs() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url="/openapi.json",
            title="meniscope API",
            swagger_js_url="/docs-assets/swagger-ui-bundle.js",
            swagger_css_url="/docs-assets/swagger-ui.css",
            swagger_favicon_url="/docs-assets/favicon-32x32.png",
        )

    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_middleware(
        Guard, hosts=settings.allowed_hosts or default_hosts(settings.host), origins=settings.allowed_origins
    )
    return app


async def _http_error(request: Request, exc: Exception) -> Response:
    """FastAPI's error answer, with a 405's ``Allow`` listing every method of the path (Starlette names only
    those of the first route that matched it: GET of /api/v1/config, not PUT)."""
    assert isinstance(exc, StarletteHTTPException)
    if exc.status_code == 405:
        methods = sorted(
            {
                m
                for route in request.app.routes
                if route.matches(request.scope)[0] == Match.PARTIAL
                for m in getattr(route, "methods", None) or ()
            }
        )
        exc = StarletteHTTPException(405, exc.detail, {"Allow": ", ".join(methods)})
    return await http_exception_handler(request, exc)
