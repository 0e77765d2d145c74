"""``meniscope bench refine``'s comparison of REPORTs: the runners must give the same windows, and when they do
not, the benchmark says which window and field differ."""

from __future__ import annotations

from service.bench.refine import differences, markdown


def test_the_same_windows_have_no_differences() -> None:
    windows = [{"index": 0, "status": "ok", "modes": [{"frequency_hz": 700.0}]}]
    assert differences(windows, [dict(w) for w in windows]) == []


def test_a_differing_field_is_named_with_its_window_and_both_values() -> None:
    first = [{"index": 0, "status": "ok"}, {"index": 1, "status": "ok", "offset_mm": 0.01}]
    other = [{"index": 0, "status": "ok"}, {"index": 1, "status": "failed", "offset_mm": 0.01}]
    assert differences(first, other) == ["window 1 status: 'ok' against 'failed'"]


def test_a_missing_window_is_a_difference() -> None:
    assert differences([{"index": 0}], []) == ["0 windows against 1"]


def test_the_table_gives_each_run_s_cpu_per_window_and_load_and_marks_a_differing_report() -> None:
    run = {"windows": 4, "seconds": 40.0, "windows_per_s": 0.1, "cpu_s_per_window": 19.5, "load": 2.25}
    results = {
        "recording": "rec4.cine",
        "cores": 2,
        "runs": [
            {**run, "name": "local pool, 2 processes", "same_report": True, "differences": []},
            {
                **run,
                "name": "Dask, 1 worker process(es)",
                "windows_per_s": 0.05,
                "same_report": False,
                "differences": ["window 1 status: 'ok' against 'failed'"],
            },
        ],
    }
    table = markdown(results)
    assert "| local pool, 2 processes | 4 | 40.0 | 0.10 | 1.00 | 19.5 | 2.2 | yes |" in table
    assert "| Dask, 1 worker process(es) | 4 | 40.0 | 0.05 | 0.50 | 19.5 | 2.2 | NO |" in table
    assert "- Dask, 1 worker process(es): window 1 status: 'ok' against 'failed'" in table
