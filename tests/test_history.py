"""The window history: SQLite in WAL mode, kept across restarts, pruned by age and by count."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

from service.analysis.results import WindowResult
from service.server.history import History


def result(index: int) -> WindowResult:
    return WindowResult(
        index=index,
        start_frame=190 * index,
        end_frame=190 * (index + 1),
        status="settled",
        reason="no oscillation above the noise",
        offset_mm=0.01,
        settling_time_s=0.0,
        settled=True,
    )


def test_windows_survive_a_restart_and_ids_keep_growing(tmp_path: Path) -> None:
    db = tmp_path / "history.sqlite"
    first = History(db, days=7, max_windows=100)
    ids = [first.add(result(k), "demo", 19000.0) for k in range(3)]
    first.close()
    again = History(db, days=7, max_windows=100)
    assert [w.result for w in again.since(0)] == [result(k) for k in range(3)]
    assert again.add(result(3), "demo", 19000.0) > max(ids)
    assert sqlite3.connect(db).execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_since_and_limit_page_through_oldest_first_latest_gives_the_newest(tmp_path: Path) -> None:
    h = History(tmp_path / "h.sqlite", days=7, max_windows=100)
    ids = [h.add(result(k), "demo", 19000.0) for k in range(10)]
    assert [w.id for w in h.since(ids[2], limit=3)] == ids[3:6]
    assert [w.id for w in h.latest(limit=2)] == ids[-2:]
    assert h.get(ids[4]).result == result(4) and h.get(12345) is None


def test_retention_drops_windows_past_the_age_or_beyond_the_count(tmp_path: Path) -> None:
    h = History(tmp_path / "h.sqlite", days=1, max_windows=5)
    old = h.add(result(0), "demo", 19000.0, stored=1000.0)
    ids = [h.add(result(k), "demo", 19000.0) for k in range(1, 8)]
    assert h.prune() == 3  # the day-old one and the two beyond the newest five
    assert h.get(old) is None and [w.id for w in h.since(0)] == ids[-5:]


def test_a_page_sent_from_the_stored_json_equals_the_windows_parsed_and_dumped(tmp_path: Path) -> None:
    """What GET /api/v1/windows sends without parsing each window again is what parsing would have made."""
    h = History(tmp_path / "h.sqlite", days=7, max_windows=100)
    ids = [h.add(result(k), 'a "quoted" source\\', 19000.0) for k in range(6)]
    for after, limit, rows in ((None, 4, h.latest(4)), (ids[1], 3, h.since(ids[1], 3)), (ids[-1], 5, [])):
        expected = {"windows": [r.to_json() for r in rows], "last_id": rows[-1].id if rows else after}
        assert json.loads(h.page_json(after, limit)) == expected
    empty = History(tmp_path / "empty.sqlite", days=7, max_windows=100)
    assert json.loads(empty.page_json(None, 5)) == {"windows": [], "last_id": None}


def test_a_window_written_again_after_a_failed_attempt_is_stored_once(tmp_path: Path) -> None:
    h = History(tmp_path / "h.sqlite", days=7, max_windows=100)
    window_id = h.new_id()
    h.add(result(0), "demo", 19000.0, window_id=window_id)
    h.add(result(0), "demo", 19000.0, window_id=window_id)  # the publishers retry a write they saw fail
    assert [w.id for w in h.since(0)] == [window_id]
