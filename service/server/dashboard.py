"""The dashboard page: static HTML and JavaScript (no build step, no libraries) fed by /ws and REST."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import FileResponse

from service.server.static_files import STATIC

router = APIRouter()


@router.get("/", include_in_schema=False)
def index() -> FileResponse:
    return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})
