"""The web layer of ``meniscope serve``: app factory, REST and WebSocket routes, publishers, history, metrics."""
from service.server.app import Service, create_app

__all__ = ["Service", "create_app"]
