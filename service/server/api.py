"""REST routes: health and readiness, status, window history, configuration, latest frame, metrics, WebSocket.

Reading needs nothing; changing (PUT /api/v1/config, POST /api/v1/ejections) needs ``Authorization: Bearer <token>`` whenever a
token is set, and a token must be set before anything can be changed on a service that is reachable
from other machines (bound beyond loopback). Every error answers ``{"detail": ...}`` as documented in
the OpenAPI schema (422: the list of problems, as for any request that fails validation).
"""

from __future__ import annotations

import dataclasses
import secrets
import time
from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request, Response, WebSocket
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError

from service.analysis.results import WindowResult
from service.errors import MeniscopeError
from service.pipeline.runtime import LatestFrame
from service.server.components import Service
from service.server.settings import Method, ServiceSettings, resolve_source
from service.sources import probe_source

#: Largest window id (SQLite's integers are signed 64-bit).
MAX_ID = 2**63 - 1
#: Largest frame index an ejection may name: the largest integer a JSON number holds exactly (a double), 15,000
#: years of frames at 19,000 frames/s; beyond it a schema's maximum and the value compared differ in rounding.
MAX_FRAME = 2**53 - 1
#: Most windows one history page returns (about 1 kB each).
MAX_PAGE = 1000


class Problem(BaseModel):
    """An error's body."""

    detail: str


def _documented(*codes: int) -> dict[int | str, dict[str, Any]]:
    descriptions = {
        400: "Host header not one the service answers to",
        401: "missing or wrong bearer token",
        403: "changing settings needs a token on this service",
        404: "not found",
        413: "request body too large",
        503: "not available now (see detail)",
    }
    return {code: {"model": Problem, "description": descriptions[code]} for code in (400, 413, *codes)}


router = APIRouter(responses=_documented())


def _service(request: Request) -> Service:
    return request.app.state.service


Svc = Annotated[Service, Depends(_service)]


def require_token(request: Request, service: Svc) -> None:
    """Allow a change only with the configured bearer token, or on loopback when none is configured."""
    token = service.settings.token
    if token is None:
        if service.settings.loopback:
            return
        raise HTTPException(
            403, "changing settings on a service reachable from other machines needs a token: set MENISCOPE_TOKEN"
        )
    given = request.headers.get("authorization", "")
    if not secrets.compare_digest(given.encode(), f"Bearer {token.get_secret_value()}".encode()):
        raise HTTPException(401, "missing or wrong bearer token", headers={"WWW-Authenticate": "Bearer"})


@router.get("/healthz", tags=["health"])
def healthz() -> dict[str, str]:
    """The process answers (it may not be ready)."""
    return {"status": "ok"}


@router.get("/readyz", tags=["health"], responses=_documented(503))
def readyz(service: Svc) -> JSONResponse:
    """200 while frames flow through a loaded model; 503 with the reason otherwise."""
    health = service.health()
    return JSONResponse(
        {"ready": health.ready, "state": health.state, "reason": health.reason},
        status_code=200 if health.ready else 503,
    )


@router.get("/api/v1/status", tags=["status"])
def status(service: Svc) -> dict[str, Any]:
    """Source, frame rates in and out, frame and window counts, model, uptime."""
    health, s, settings = service.health(), service.stats, service.settings
    return {
        "ready": health.ready,
        "state": health.state,
        "reason": health.reason,
        "attempts": health.attempts,
        "source": health.source,
        "fps_in": round(s.fps_in, 1),
        "fps_out": round(s.fps_out, 1),
        "frames": {
            "acquired": s.frames_acquired,
            "inferred": s.frames_inferred,
            "dropped": s.frames_dropped,
            "gaps": s.frame_gaps,
            "lost_upstream": s.frames_lost_upstream,
        },
        "windows": {"closed": s.windows_closed, "skipped": s.windows_skipped, "unpublished": service.unpublished},
        "history": dataclasses.asdict(service.history_health()),
        "model": {"dir": str(settings.models), "method": settings.method},
        "zmq_publish": service.zmq_endpoint,
        "pipeline_process": {
            "pid": service.pipeline.pid if service.pipeline else None,
            "restarts": service.pipeline.restarts if service.pipeline else 0,
        },
        "uptime_s": round(time.time() - service.started, 3),
    }


class StoredWindowBody(BaseModel):
    """A stored window result: its id, when it was stored (s since the epoch), source, frame rate, the method that
    made it, its revision (0 as first published, 1 refined by ``serve --refine``'s lane) and the refinement's
    latency."""

    id: int
    stored: float
    source: str
    fps: float
    method: str | None = Field(description="per-frame method; +synthesis once refined; null in older histories")
    revision: int = Field(ge=0, description="0 as first published, 1 refined (the same id, replaced)")
    refined: bool
    refine_latency_s: float | None = Field(description="refined: closing frame read -> refined update published")
    window: WindowResult


class WindowsPage(BaseModel):
    windows: list[StoredWindowBody]
    last_id: int | None = Field(description="the last id of this page (``since`` again when empty)")


@router.get("/api/v1/windows", tags=["windows"], response_model=WindowsPage, response_class=Response)
def windows(
    service: Svc,
    since: Annotated[int | None, Query(ge=0, le=MAX_ID, description="only ids above this")] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE)] = 100,
) -> Response:
    """Stored window results: after id ``since`` (oldest first), or else the newest ``limit``. Sent as stored,
    without parsing them again: a large page costs the web side little."""
    page = service.history.page_json(since, limit)
    return Response(page, media_type="application/json")


@router.get(
    "/api/v1/windows/{window_id}", tags=["windows"], response_model=StoredWindowBody, responses=_documented(404)
)
def window(window_id: Annotated[int, Path(ge=0, le=MAX_ID)], service: Svc) -> dict[str, Any]:
    row = service.history.get(window_id)
    if row is None:
        raise HTTPException(404, f"no window {window_id} (never stored, or past retention)")
    return row.to_json()


class ConfigChange(BaseModel):
    """What PUT /api/v1/config may change."""

    model_config = ConfigDict(extra="forbid")
    source: str | None = Field(
        None, min_length=1, max_length=4096, description="source URI or recording path (docs/service.md)"
    )
    method: Method | None = None


@router.get("/api/v1/config", tags=["config"])
def get_config(service: Svc) -> dict[str, Any]:
    return service.settings.public()


@router.put("/api/v1/config", tags=["config"], dependencies=[Depends(require_token)], responses=_documented(401, 403))
def put_config(change: ConfigChange, service: Svc) -> dict[str, Any]:
    """Change the source and/or the inverse method; the pipeline restarts with them. A new source is checked
    first (its scheme, options and, for a recording, the file itself): one that cannot open is refused with 422
    and the running one kept. A camera or socket is opened only by the pipeline: when it then fails, the
    service says why in /readyz and retries it, as for any source."""
    current: ServiceSettings = service.settings
    updates = change.model_dump(exclude_unset=True)
    try:
        settings = ServiceSettings(**{**dict(current), **updates})
        if change.source is not None and change.source != current.source:
            probe_source(resolve_source(change.source, settings.recordings_folder))
    except ValidationError as exc:
        raise RequestValidationError(
            [
                {**err, "loc": ("body", *err["loc"])}
                for err in exc.errors(include_url=False, include_context=False, include_input=False)
            ]
        ) from None
    except MeniscopeError as exc:
        raise RequestValidationError([{"loc": ("body", "source"), "msg": str(exc), "type": "value_error"}]) from None
    service.reconfigure(settings)
    return settings.public()


def _not_bool(value: Any) -> Any:
    """A number as JSON gives it, never ``true``/``false`` (which pydantic would read as 1 and 0)."""
    if isinstance(value, bool):
        raise ValueError("a boolean is not a number")
    return value


_NOT_BOOL = BeforeValidator(_not_bool)


class EjectionAtFrame(BaseModel):
    """One ejection announced by the printer by its camera frame index."""

    model_config = ConfigDict(extra="forbid")
    frame: Annotated[int, _NOT_BOOL] = Field(ge=0, le=MAX_FRAME, description="the camera's frame index of the ejection")


class EjectionAtTime(BaseModel):
    """One ejection announced by the printer by its time since the stream's frame 0."""

    model_config = ConfigDict(extra="forbid")
    time_s: Annotated[float, _NOT_BOOL] = Field(
        ge=0, allow_inf_nan=False, description="seconds since the stream's frame 0"
    )


@router.post(
    "/api/v1/ejections",
    tags=["trigger"],
    status_code=202,
    dependencies=[Depends(require_token)],
    responses=_documented(401, 403, 503),
)
def post_ejection(event: EjectionAtFrame | EjectionAtTime, service: Svc) -> dict[str, Any]:
    """The printer's trigger: one ejection (exactly one of ``frame`` and ``time_s``, as the schema says), sent on
    to the pipeline process; ``received``: the events this web process has sent on. With the setting ``trigger =
    "printer"`` the windows are cut at these, and the video's ejections check them
    (``meniscope_trigger_disagreements_total``); 503 while the pipeline process is not running (the event would
    reach no segmenter)."""
    frame, time_s = getattr(event, "frame", None), getattr(event, "time_s", None)
    if not service.eject(frame, time_s):
        raise HTTPException(503, "the pipeline process is not running: the ejection reached no segmenter")
    return {"received": service.ejections_sent}


@router.get("/api/v1/frames/latest.png", tags=["frames"], response_class=Response, responses=_documented(404))
def latest_frame(service: Svc) -> Response:
    """The last inferred frame's ROI, stretched to its brightest pixel."""
    return Response(
        service.frame_views().camera(_latest(service)), media_type="image/png", headers={"Cache-Control": "no-store"}
    )


@router.get(
    "/api/v1/frames/latest/render.png", tags=["frames"], response_class=Response, responses=_documented(404, 503)
)
def latest_render(service: Svc) -> Response:
    """The scene rendered from the last frame's inferred coefficients, stretched the same way."""
    try:
        image = service.frame_views().render(_latest(service))
    except MeniscopeError as exc:
        raise HTTPException(503, str(exc)) from None
    if image is None:
        raise HTTPException(503, "the renderer is busy (the first render compiles it)", headers={"Retry-After": "5"})
    return Response(image, media_type="image/png", headers={"Cache-Control": "no-store"})


@router.get("/api/v1/frames/latest", tags=["frames"], responses=_documented(404))
def latest_coefficients(service: Svc) -> dict[str, Any]:
    frame = _latest(service)
    d, p, a, b = frame.coefficients
    return {"index": frame.index, "d_mm": d, "p": p, "a_mm": a, "b_mm": b, "centre_mm": frame.centre_mm}


def _latest(service: Service) -> LatestFrame:
    frame = service.latest
    if frame is None:
        raise HTTPException(404, "no frame inferred yet")
    return frame


@router.get("/metrics", tags=["metrics"], response_class=Response)
def metrics(service: Svc) -> Response:
    """Prometheus text format."""
    return Response(service.metrics(), media_type=CONTENT_TYPE_LATEST)


@router.websocket("/ws")
async def ws(websocket: WebSocket) -> None:
    """Every window result as it is made, and the live trace ``trace_hz`` times a second (docs/service.md)."""
    await websocket.app.state.service.hub.serve(websocket)
