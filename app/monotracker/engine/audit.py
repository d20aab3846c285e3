"""Append-only audit log in SQLite.

Every decision and event of a session (fiducials confirmed or rejected, plan changes,
registrations, arm/disarm, tracking start/stop, alerts, faults, restarts) is one row with its
wall-clock time (Unix s and ISO-8601 UTC), the session clock, and JSON details.

Append-only is enforced by the database itself: triggers abort any ``UPDATE`` or ``DELETE`` on
the table, so neither a bug nor a careless tool can rewrite history through SQLite. The
database runs in WAL mode with ``synchronous=FULL``: a committed row survives ``kill -9`` and a
power cut. One connection is shared by the engine's threads behind a lock.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from monotracker.engine.events import Event

_SCHEMA = """
CREATE TABLE IF NOT EXISTS audit (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    t_unix REAL NOT NULL,
    t_iso TEXT NOT NULL,
    t_session REAL,
    session_id TEXT NOT NULL,
    kind TEXT NOT NULL,
    level TEXT NOT NULL,
    code TEXT NOT NULL,
    message TEXT NOT NULL,
    data TEXT NOT NULL
);
CREATE TRIGGER IF NOT EXISTS audit_no_update BEFORE UPDATE ON audit
BEGIN SELECT RAISE(ABORT, 'audit log is append-only'); END;
CREATE TRIGGER IF NOT EXISTS audit_no_delete BEFORE DELETE ON audit
BEGIN SELECT RAISE(ABORT, 'audit log is append-only'); END;
"""


@dataclass(frozen=True)
class AuditEntry:
    id: int
    t_unix: float
    t_iso: str
    t_session: float | None
    session_id: str
    kind: str
    level: str
    code: str
    message: str
    data: dict


class AuditLog:
    """The audit database at ``path`` (created if missing). Thread-safe."""

    def __init__(self, path: Path, session_id: str):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.session_id = session_id
        self._lock = threading.Lock()
        self._db = sqlite3.connect(str(self.path), check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.executescript(_SCHEMA)

    def record(self, kind: str, level: str, code: str, message: str, data: dict | None = None,
               t_unix: float | None = None, t_session: float | None = None) -> int:
        """Append one row; returns its id."""
        t = time.time() if t_unix is None else float(t_unix)
        iso = datetime.fromtimestamp(t, tz=timezone.utc).isoformat(timespec="milliseconds")
        payload = json.dumps(data or {}, default=_json_default, sort_keys=True)
        with self._lock:
            if self._db is None:
                raise RuntimeError("audit log is closed")
            cur = self._db.execute(
                "INSERT INTO audit (t_unix, t_iso, t_session, session_id, kind, level, code, message, data)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (t, iso, t_session, self.session_id, kind, level, code, message, payload),
            )
            return int(cur.lastrowid)

    def record_event(self, ev: Event) -> int:
        """Sink for :class:`~monotracker.engine.events.EventBus`."""
        return self.record(ev.kind, ev.level, ev.code, ev.message, ev.data, t_unix=ev.t, t_session=ev.t_session)

    def entries(self, code: str | None = None, kind: str | None = None, session_id: str | None = None,
                limit: int | None = None) -> list[AuditEntry]:
        """Rows oldest first, optionally filtered; ``limit`` keeps the newest ``limit``."""
        where, args = [], []
        for col, val in (("code", code), ("kind", kind), ("session_id", session_id)):
            if val is not None:
                where.append(f"{col} = ?")
                args.append(val)
        sql = "SELECT id, t_unix, t_iso, t_session, session_id, kind, level, code, message, data FROM audit"
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY id DESC"
        if limit is not None:
            sql += f" LIMIT {int(limit)}"
        with self._lock:
            rows = self._db.execute(sql, args).fetchall()
        return [AuditEntry(*r[:9], json.loads(r[9])) for r in reversed(rows)]

    def close(self) -> None:
        with self._lock:
            if self._db is not None:
                self._db.close()
                self._db = None


def _json_default(o):
    try:
        import numpy as np

        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
