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


def samples(values: np.ndarray, decimals: int = 6) -> list[float | None]:
    """``values`` (mm) as JSON numbers rounded to ``decimals`` (1 nm), null where not finite."""
    rounded = np.round(np.asarray(values, dtype=np.float64), decimals)
    return [float(v) if np.isfinite(v) else None for v in rounded]


def window_message(stored: StoredWindow, values: np.ndarray | None = None) -> str:
    """A window message: ``{"schema", "type": "window", "id", "stored", "source", "fps", "window"}``,
    plus ``"values"`` (the samples, mm) when given."""
    message: dict[str, Any] = {"schema": WINDOW_SCHEMA, "type": "window", **stored.to_json()}
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
