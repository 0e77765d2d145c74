"""Window results kept in SQLite (write-ahead log) across restarts, pruned by age and count.

One row per published window: an id that only grows (what REST's ``since`` and the published
messages carry), the time it was stored, the source and frame rate, and the :class:`WindowResult`
as JSON, with the method that made it, its revision (0: as first published; 1: refined by the lane of
``serve --refine``, which replaces the row under the same id) and the refinement's latency. One writer (the publishers, which give each window its id before sending it and store it
after) and any number of readers (REST requests, each with a short-lived connection of its own),
which WAL lets run side by side.
"""

from __future__ import annotations

import json
import sqlite3
import time
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from service.analysis.results import WindowResult
from service.errors import MeniscopeError

SCHEMA = """
CREATE TABLE IF NOT EXISTS windows (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    stored REAL NOT NULL,         -- seconds since the epoch
    source TEXT NOT NULL,
    fps REAL NOT NULL,
    result TEXT NOT NULL,         -- WindowResult as JSON
    method TEXT,                  -- the method that made it (null in databases older than the column)
    revision INTEGER NOT NULL DEFAULT 0,  -- 0 as first published, 1 refined (same id)
    refine_latency_s REAL         -- a refined window's: closing frame read -> refined update published
);
CREATE INDEX IF NOT EXISTS windows_stored ON windows (stored);
"""
#: Columns added since the first schema, with their definitions: added to an older database when it opens.
ADDED = {"method": "TEXT", "revision": "INTEGER NOT NULL DEFAULT 0", "refine_latency_s": "REAL"}
#: Inserts between two retention passes.
PRUNE_EVERY = 500


@dataclass(frozen=True)
class StoredWindow:
    """A window result as kept: its id, when it was stored (s since the epoch), source and frame rate, the method
    that made it, its revision (0 first, 1 refined) and, refined, how long after its window closed."""

    id: int
    stored: float
    source: str
    fps: float
    result: WindowResult
    method: str | None = None
    revision: int = 0
    refine_latency_s: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "stored": self.stored,
            "source": self.source,
            "fps": self.fps,
            "method": self.method,
            "revision": self.revision,
            "refined": self.revision > 0,
            "refine_latency_s": self.refine_latency_s,
            "window": self.result.model_dump(mode="json"),
        }


class History:
    """The database at ``path``, keeping windows for ``days`` and at most ``max_windows`` of them."""

    def __init__(self, path: Path, days: float, max_windows: int) -> None:
        self.path, self.days, self.max_windows = Path(path), days, max_windows
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._writer = self._connect(check_same_thread=False)  # used by one thread at a time
            self._writer.execute("PRAGMA journal_mode=WAL")
            self._writer.execute("PRAGMA synchronous=NORMAL")  # WAL: durable at checkpoints, no fsync per window
            self._writer.executescript(SCHEMA)
            have = {row["name"] for row in self._writer.execute("PRAGMA table_info(windows)")}
            for column, definition in ADDED.items():
                if column not in have:
                    self._writer.execute(f"ALTER TABLE windows ADD COLUMN {column} {definition}")
        except (OSError, sqlite3.Error) as exc:
            raise MeniscopeError(self.path, f"cannot open the history database: {exc}") from None
        self._inserts = 0
        self._last_id = self._writer.execute(  # AUTOINCREMENT's record of the largest id ever given, pruned or not
            "SELECT MAX(COALESCE((SELECT seq FROM sqlite_sequence WHERE name = 'windows'), 0), "
            "COALESCE((SELECT MAX(id) FROM windows), 0))"
        ).fetchone()[0]
        self.prune()

    def _connect(self, check_same_thread: bool = True) -> sqlite3.Connection:
        conn = sqlite3.connect(self.path, timeout=5.0, check_same_thread=check_same_thread, isolation_level=None)
        conn.row_factory = sqlite3.Row
        return conn

    def new_id(self) -> int:
        """The id of the next window, given now so that a window can be published before it is stored (from one
        thread at a time)."""
        self._last_id += 1
        return self._last_id

    def add(
        self,
        result: WindowResult,
        source: str,
        fps: float,
        stored: float | None = None,
        window_id: int | None = None,
        method: str | None = None,
        revision: int = 0,
        refine_latency_s: float | None = None,
    ) -> int:
        """Store one result under ``window_id`` (from :meth:`new_id`; a new one if None); its id. A window stored
        again under its id (after a failed attempt, or refined) replaces the row."""
        window_id = self.new_id() if window_id is None else window_id
        self._writer.execute(
            "INSERT OR REPLACE INTO windows (id, stored, source, fps, result, method, revision, refine_latency_s) "
            "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
            (
                window_id,
                time.time() if stored is None else stored,
                source,
                fps,
                result.model_dump_json(),
                method,
                revision,
                refine_latency_s,
            ),
        )
        self._inserts += 1
        if self._inserts % PRUNE_EVERY == 0:
            self.prune()
        return window_id

    def prune(self, now: float | None = None) -> int:
        """Delete windows older than ``days`` or beyond the newest ``max_windows``; how many went."""
        cutoff = (time.time() if now is None else now) - self.days * 86400.0
        cursor = self._writer.execute(
            "DELETE FROM windows WHERE stored < ? OR id <= (SELECT MAX(id) FROM windows) - ?",
            (cutoff, self.max_windows),
        )
        return cursor.rowcount

    def since(self, after: int = 0, limit: int = 100) -> list[StoredWindow]:
        """Windows with id above ``after``, oldest first, at most ``limit``."""
        return [_stored(row) for row in self._rows(after, limit)]

    def latest(self, limit: int = 100) -> list[StoredWindow]:
        """The newest ``limit`` windows, oldest first."""
        return [_stored(row) for row in self._rows(None, limit)]

    def page_json(self, after: int | None, limit: int) -> bytes:
        """``{"windows": [...], "last_id": ...}`` for :meth:`since` (``after`` given) or :meth:`latest`, made from
        the stored JSON as it is: no result is parsed and dumped again (10,000 windows: 0.9 s of interpreter time
        that the frame path waited for)."""
        rows = self._rows(after, limit)
        items = ",".join(
            f'{{"id":{row["id"]},"stored":{json.dumps(row["stored"])},"source":{json.dumps(row["source"])},'
            f'"fps":{json.dumps(row["fps"])},"method":{json.dumps(row["method"])},"revision":{row["revision"]},'
            f'"refined":{json.dumps(row["revision"] > 0)},"refine_latency_s":{json.dumps(row["refine_latency_s"])},'
            f'"window":{row["result"]}}}'
            for row in rows
        )
        last = rows[-1]["id"] if rows else after
        return f'{{"windows":[{items}],"last_id":{json.dumps(last)}}}'.encode()

    def _rows(self, after: int | None, limit: int) -> list[sqlite3.Row]:
        """Rows with id above ``after`` (oldest first), or the newest ``limit`` when ``after`` is None."""
        with self._reader() as conn:
            if after is not None:
                return conn.execute("SELECT * FROM windows WHERE id > ? ORDER BY id LIMIT ?", (after, limit)).fetchall()
            return conn.execute(
                "SELECT * FROM (SELECT * FROM windows ORDER BY id DESC LIMIT ?) ORDER BY id", (limit,)
            ).fetchall()

    def get(self, window_id: int) -> StoredWindow | None:
        with self._reader() as conn:
            row = conn.execute("SELECT * FROM windows WHERE id = ?", (window_id,)).fetchone()
        return None if row is None else _stored(row)

    def _reader(self) -> closing[sqlite3.Connection]:
        """A connection of its own for one read, closed after it."""
        return closing(self._connect())

    def close(self) -> None:
        self._writer.close()


def _stored(row: sqlite3.Row) -> StoredWindow:
    return StoredWindow(
        row["id"],
        row["stored"],
        row["source"],
        row["fps"],
        WindowResult.model_validate(json.loads(row["result"])),
        row["method"],
        row["revision"],
        row["refine_latency_s"],
    )
