"""Published messages are plain JSON: missing samples are null, never NaN or Infinity."""

from __future__ import annotations

import json

import numpy as np

from service.analysis.results import WindowResult
from service.pipeline.runtime import TraceSnippet
from service.server.history import StoredWindow
from service.server.messages import trace_message, window_message


def strict(text: str) -> dict:
    def refuse(constant: str) -> None:
        raise AssertionError(f"{constant} in a published message")

    return json.loads(text, parse_constant=refuse)


def test_a_trace_with_lost_frames_has_nulls_where_they_were() -> None:
    values = np.array([0.01, np.nan, np.inf, -0.0123456789])
    message = strict(trace_message(TraceSnippet(1000, 19000.0, values, [1002])))
    assert message == {
        "schema": "meniscope.trace/1",
        "type": "trace",
        "first_index": 1000,
        "fps": 19000.0,
        "values": [0.01, None, None, -0.012346],
        "ejections": [1002],
    }


def test_a_window_message_carries_the_stored_result_and_its_samples() -> None:
    result = WindowResult(index=3, start_frame=190, end_frame=193, status="failed", reason="too short")
    stored = StoredWindow(7, 1.5e9, "demo", 19000.0, result)
    message = strict(window_message(stored, np.array([0.02, np.nan, 0.01])))
    assert message["id"] == 7 and message["window"] == result.model_dump(mode="json")
    assert message["values"] == [0.02, None, 0.01]
    assert "values" not in strict(window_message(stored))
