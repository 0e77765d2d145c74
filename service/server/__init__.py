"""The web layer of ``meniscope serve``: app factory, REST and WebSocket routes, publishers, history, metrics."""
from service.server.app import create_app
from service.server.components import Service

__all__ = ["Service", "create_app"]
