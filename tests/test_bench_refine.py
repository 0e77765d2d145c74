"""``meniscope bench refine``'s comparison of REPORTs: the runners must give the same windows, and when they do
not, the benchmark says which window and field differ."""

from __future__ import annotations

from service.bench.refine import differences


def test_the_same_windows_have_no_differences() -> None:
    windows = [{"index": 0, "status": "ok", "modes": [{"frequency_hz": 700.0}]}]
    assert differences(windows, [dict(w) for w in windows]) == []


def test_a_differing_field_is_named_with_its_window_and_both_values() -> None:
    first = [{"index": 0, "status": "ok"}, {"index": 1, "status": "ok", "offset_mm": 0.01}]
    other = [{"index": 0, "status": "ok"}, {"index": 1, "status": "failed", "offset_mm": 0.01}]
    assert differences(first, other) == ["window 1 status: 'ok' against 'failed'"]


def test_a_missing_window_is_a_difference() -> None:
    assert differences([{"index": 0}], []) == ["0 windows against 1"]
