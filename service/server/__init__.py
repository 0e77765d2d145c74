"""The web layer of ``meniscope serve`` and its settings: app factory (``app``), REST and WebSocket routes,
the pipeline's process (``engine``, ``pipeline_process``), publishers, history, metrics.

Nothing is imported here, so that ``service.server.settings`` loads without the web framework."""
