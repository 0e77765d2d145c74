"""The inverse method a setting names, opened for a scene: ONNX networks or a nearest-neighbour search."""
from __future__ import annotations

from service.inverse.base import InverseMethod
from service.inverse.nearest import NearestDatabase, NearestMethod
from service.inverse.network import NetworkMethod
from service.scene import Scene
from service.settings import ServiceSettings


def open_method(settings: ServiceSettings, scene: Scene) -> InverseMethod:
    """``network`` / ``direct`` from ``settings.models``; ``nearest`` / ``nearest-approx`` from
    ``settings.nearest_database`` (slower, and as good as the database is dense)."""
    if settings.method in ("network", "direct"):
        return NetworkMethod(settings.models, scene, settings.method, threads=settings.threads, batch=settings.batch)
    assert settings.nearest_database is not None  # the settings refuse a nearest method without one
    return NearestMethod(NearestDatabase.load(settings.nearest_database), exact=settings.method == "nearest")
