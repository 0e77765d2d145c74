"""The inverse methods by name, as settings, REPORT.json and benchmarks call them, and how each is opened.

- ``network``: VAE encoder + regressor (ONNX), the fast default;
- ``direct``: the CNN trained end to end on renders (ONNX), the paper's counter-example;
- ``nearest`` / ``nearest-approx``: the nearest render of a database, exact or PCA + FLANN search;
- ``regularised``: the 10 nearest renders of each frame, one damped sinusoid through them per window
  (a window-level method: :mod:`service.analysis.offline` runs it once the windows are known).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from service.errors import MeniscopeError

if TYPE_CHECKING:  # the methods load onnxruntime and scipy: imported when one is opened, not to list their names
    from service.inverse.base import InverseMethod
    from service.inverse.nearest import NearestDatabase
    from service.scene import Scene

METHODS = ("network", "direct", "nearest", "nearest-approx", "regularised")
#: Methods that need a render database (``meniscope dataset``).
DATABASE_METHODS = ("nearest", "nearest-approx", "regularised")
#: Where a model folder keeps its database when it has one.
DATABASE_DIR = "database"


def database_folder(models: Path, database: Path | None) -> Path:
    """The database a nearest-neighbour method searches: ``database`` if given, else MODELS/database."""
    folder = database if database is not None else models / DATABASE_DIR
    if not folder.is_dir():
        raise MeniscopeError(
            folder,
            f"no render database there: build one with `meniscope dataset --out {folder}` or name one with --database",
        )
    return folder


def open_method(
    name: str, scene: Scene, models: Path, database: Path | None = None, threads: int = 1, batch: int = 64
) -> tuple[InverseMethod, NearestDatabase | None]:
    """The per-frame method behind ``name`` and, for the nearest-neighbour ones, its database.

    ``threads``: a graph's onnxruntime threads, one by default as in ``serve`` (its settings' ``threads``): the graph
    has a thread of its own in both pipelines, and a second onnxruntime thread cost CPU for no more frames/s
    (docs/benchmarks.md).

    ``regularised`` returns the exact nearest method (its per-frame fallback) with the database
    whose candidates the window fit chooses among.
    """
    from service.inverse.nearest import NearestMethod
    from service.inverse.network import NetworkMethod

    if name not in METHODS:
        raise MeniscopeError("--method", f"unknown method {name!r}; choose one of {', '.join(METHODS)}")
    if name not in DATABASE_METHODS:
        return NetworkMethod(models, scene, name, threads=threads, batch=batch), None
    db = open_database(database_folder(models, database), scene)
    return NearestMethod(db, exact=name != "nearest-approx"), db


def open_database(folder: Path, scene: Scene) -> NearestDatabase:
    """The render database in ``folder``, refused unless its renders are the scene's ROI (the frames searched)
    and were made for this scene (its sha256, as a model folder's manifest is checked)."""
    from service.inverse.nearest import NearestDatabase

    db = NearestDatabase.load(folder)
    if db.shape != (scene.camera.height_px, scene.camera.width_px):
        raise MeniscopeError(
            folder,
            f"renders of {db.shape[1]}x{db.shape[0]} px do not match the scene's ROI "
            f"{scene.camera.width_px}x{scene.camera.height_px}",
        )
    made_for = NearestDatabase.scene_sha256(folder)
    if made_for != scene.sha256:
        raise MeniscopeError(
            folder,
            f"rendered for scene {made_for[:12]}, not this one ({scene.sha256[:12]}): "
            "build a database for this scene with `meniscope database --scene ...`",
        )
    return db
