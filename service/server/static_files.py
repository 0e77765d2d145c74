"""Where the dashboard's files are: ``service/server/static`` (package data)."""

from importlib.resources import files
from pathlib import Path

STATIC = Path(str(files("service") / "server" / "static"))
