"""The published message formats (docs/service.md): one JSON object per window result or trace snippet.

Window messages are what the WebSocket, the ZeroMQ PUB socket and REST share; the WebSocket's also
carry the window's samples, for drawing. Numbers are plain JSON numbers: missing samples are null,
never NaN (the :class:`WindowResult` itself holds only finite numbers).
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from service.pipeline.runtime import TraceSnippet
from service.server.history import StoredWindow

#: The ``schema`` of every window message.
WINDOW_SCHEMA = "meniscope.window/1"
#: The ``schema`` of every trace message.
TRACE_SCHEMA = "meniscope.trace/1"
#: The ZeroMQ topic (first message part) of window results.
WINDOW_TOPIC = b"meniscope.window"
#: The ZeroMQ topic of refined updates of windows already published (``serve --refine``): not a prefix match of
#: :data:`WINDOW_TOPIC`, so that a subscriber to windows alone never takes an update for a new window.
REFINED_TOPIC = b"meniscope.refined"
#: The ``type`` of a window message, and of a refined update of one (same id; dashboards replace the window).
WINDOW, WINDOW_UPDATE = "window", "window_update"


def samples(values: np.ndarray, decimals: int = 6) -> list[float | None]:
    """``values`` (mm) as JSON numbers rounded to ``decimals`` (1 nm), null where not finite."""
    rounded = np.round(np.asarray(values, dtype=np.float64), decimals)
    return [float(v) if np.isfinite(v) else None for v in rounded]


def window_message(stored: StoredWindow, values: np.ndarray | None = None) -> str:
    """A window message: ``{"schema", "type", "id", "stored", "source", "fps", "method", "revision", "refined",
    "refine_latency_s", "window"}``, of type ``window`` or, refined (revision 1), ``window_update``; plus
    ``"values"`` (the samples, mm) when given."""
    kind = WINDOW_UPDATE if stored.revision else WINDOW
    message: dict[str, Any] = {"schema": WINDOW_SCHEMA, "type": kind, **stored.to_json()}
    if values is not None:
        message["values"] = samples(values)
    return json.dumps(message, allow_nan=False, separators=(",", ":"))


def trace_message(trace: TraceSnippet) -> str:
    """A trace message: the latest frames' centre displacement at full rate and the ejections among them."""
    return json.dumps(
        {
            "schema": TRACE_SCHEMA,
            "type": "trace",
            "first_index": trace.first_index,
            "fps": trace.fps,
            "values": samples(trace.values),
            "ejections": trace.ejections,
        },
        allow_nan=False,
        separators=(",", ":"),
    )
