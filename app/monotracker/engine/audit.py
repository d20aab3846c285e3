"""Append-only, tamper-evident audit log in SQLite, written off the safety path.

Every decision and event of a session (fiducials confirmed or rejected, plan changes,
registrations, arm/disarm, tracking start/stop, alerts, faults, restarts) is one row with its
wall-clock time (Unix s and ISO-8601 UTC), the session clock, and JSON details.

Never blocks safety: :meth:`AuditLog.record` only puts the row on a bounded queue; a writer
thread of its own commits it. A stop, hold or alarm never waits on the database. When the
database is locked by another process, full, read-only or cannot be opened, rows go to a
JSON-lines spill file beside it (``audit.spill.jsonl``; if the folder is not writable, one in the
system's temp folder); once the database takes writes again (or at the next session's first
write) the spilled rows are copied into the chain, with an ``audit_spill_ingested`` row holding
the spill file's hash (so a crash in between cannot copy them twice), and the file is renamed
``audit.spill-ingested-*.jsonl``. ``on_problem(level, code, message, data)`` is told how many rows are
delayed (spilled) or lost (the queue overflowed or even the spill failed): the session raises that
as an ``audit_delayed`` / ``audit_lost`` alarm. :meth:`AuditLog.flush` waits (bounded) until the
queue is written, for readers that want every row so far.

Tamper evidence: each row carries ``hash = sha256(prev_hash + canonical row)``, chained to the
previous row's hash (the first row chains to 64 zeros). Triggers abort ``UPDATE``, ``DELETE`` and
an ``INSERT`` (``OR REPLACE``) over an existing id. :func:`verify` (``monotracker audit verify``)
recomputes the chain, checks the ids are consecutive and the triggers present, and names the first
bad row. Limits (written down): the hash is not keyed, so someone who rewrites the whole file
and recomputes every hash is not detected, and removing the newest rows leaves a valid shorter
chain; the chain proves the rows were not edited in place, not that the file is the original.

The database runs in WAL mode with ``synchronous=FULL``: a committed row survives ``kill -9``
and a power cut; rows still on the queue at a crash (at most a few ms of events) are lost.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import queue
import sqlite3
import tempfile
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from monotracker.engine.events import Event

log = logging.getLogger(__name__)

GENESIS = "0" * 64
TRIGGERS = ("audit_no_update", "audit_no_delete", "audit_no_replace")
_COLS = "id, t_unix, t_iso, t_session, session_id, kind, level, code, message, data"

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
CREATE TRIGGER IF NOT EXISTS audit_no_replace BEFORE INSERT ON audit
WHEN EXISTS (SELECT 1 FROM audit WHERE id = NEW.id)
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


def row_hash(prev_hash: str, row: tuple) -> str:
    """SHA-256 hex of ``prev_hash`` and the row's columns (:data:`_COLS` order) as canonical JSON."""
    body = json.dumps(list(row), separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256((prev_hash + "\n" + body).encode("utf-8")).hexdigest()


def _open_db(path: Path, timeout_s: float) -> sqlite3.Connection:
    db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None, timeout=timeout_s)
    try:
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=FULL")
        db.executescript(_SCHEMA)
        cols = {r[1] for r in db.execute("PRAGMA table_info(audit)")}
        for c in ("prev_hash", "hash"):
            if c not in cols:  # an audit log from before the chain: its old rows stay unchained
                db.execute(f"ALTER TABLE audit ADD COLUMN {c} TEXT")
    except BaseException:
        db.close()
        raise
    return db


class AuditLog:
    """The audit database at ``path`` (created if missing). Thread-safe; never raises on write.

    ``on_problem(level, code, message, data)``: called from the writer thread when rows are
    delayed (spilled) or lost, and when the database works again. ``busy_timeout_s``: how long the
    writer waits for a locked database before it spills a batch.
    """

    def __init__(self, path: Path, session_id: str, on_problem=None, queue_size: int = 10000,
                 busy_timeout_s: float = 0.5):
        self.path = Path(path)
        self.session_id = session_id
        self.spill_path = self.path.with_name("audit.spill.jsonl")
        self.on_problem = on_problem
        self.busy_timeout_s = float(busy_timeout_s)
        self.delayed = 0  # rows written to a spill file instead of the database
        self.lost = 0  # rows neither in the database nor in a spill file
        self.open_error: str | None = None
        self._q: queue.Queue = queue.Queue(maxsize=queue_size)
        self._cond = threading.Condition()
        self._pending = 0
        self._closed = False
        self._read_lock = threading.Lock()
        self._db: sqlite3.Connection | None = None  # the writer's connection
        self._reader: sqlite3.Connection | None = None
        self._last_open_try = 0.0
        self._trouble = False  # inside a delayed episode (one alarm per episode, then counts)
        self._ingest_checked = False  # spill files of earlier sessions are copied in after the first write
        self._last_alarm = 0.0
        self._try_open()
        self._thread = threading.Thread(target=self._run, name="monotracker-audit", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ opening
    def _try_open(self) -> bool:
        self._last_open_try = time.monotonic()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db = _open_db(self.path, self.busy_timeout_s)
            self.open_error = None
            return True
        except (OSError, sqlite3.Error) as exc:
            self._db = None
            self.open_error = f"{type(exc).__name__}: {exc}"
            return False

    # ------------------------------------------------------------------ writing
    def record(self, kind: str, level: str, code: str, message: str, data: dict | None = None,
               t_unix: float | None = None, t_session: float | None = None) -> None:
        """Queue one row (never blocks, never raises for a disk or database problem)."""
        t = time.time() if t_unix is None else float(t_unix)
        iso = datetime.fromtimestamp(t, tz=timezone.utc).isoformat(timespec="milliseconds")
        try:
            payload = json.dumps(data or {}, default=_json_default, sort_keys=True)
        except (TypeError, ValueError) as exc:
            payload = json.dumps({"unserialisable": str(exc)})
        row = (t, iso, t_session, self.session_id, kind, level, code, message, payload)
        with self._cond:
            if self._closed:
                self.lost += 1
                return
            self._pending += 1
        try:
            self._q.put_nowait(row)
        except queue.Full:
            with self._cond:
                self._pending -= 1
                self._cond.notify_all()
            self._spill([row], "the audit queue is full")

    def record_event(self, ev: Event) -> None:
        """Sink for :class:`~monotracker.engine.events.EventBus` (non-blocking)."""
        self.record(ev.kind, ev.level, ev.code, ev.message, ev.data, t_unix=ev.t, t_session=ev.t_session)

    def _run(self) -> None:
        while True:
            row = self._q.get()
            if row is None:
                return
            batch = [row]
            while len(batch) < 256:
                try:
                    nxt = self._q.get_nowait()
                except queue.Empty:
                    break
                if nxt is None:
                    self._q.put(None)  # stop after this batch
                    break
                batch.append(nxt)
            try:
                self._write(batch)
            except Exception:  # noqa: BLE001 - the writer must survive anything
                log.exception("audit writer failed")
                self._spill(batch, "internal error in the audit writer")
            with self._cond:
                self._pending -= len(batch)
                self._cond.notify_all()

    def _write(self, batch: list) -> None:
        if self._db is None and (time.monotonic() - self._last_open_try < 2.0 or not self._try_open()):
            self._spill(batch, f"the audit database cannot be opened ({self.open_error})")
            return
        try:
            self._insert(batch)
        except sqlite3.Error as exc:
            self._spill(batch, f"the audit database refused the write ({exc})")
            return
        if self._trouble or not self._ingest_checked:
            self._ingest_checked = True
            recovered = self._trouble
            self._trouble = False
            n = self._ingest_spills()
            if recovered:
                self._problem("info", "audit_recovered", f"audit database writable again; {n} delayed rows copied in",
                              {"delayed": self.delayed, "lost": self.lost, "ingested": n})

    def _insert(self, rows: list, check_sha: str | None = None) -> bool:
        """Append ``rows`` to the chain in one transaction. With ``check_sha``: only if no
        ``audit_spill_ingested`` row names that spill file's hash yet (False: already in)."""
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            if check_sha is not None and db.execute(
                    "SELECT 1 FROM audit WHERE code = 'audit_spill_ingested' AND data LIKE ?",
                    (f'%"{check_sha}"%',)).fetchone():
                db.execute("ROLLBACK")
                return False
            last = db.execute("SELECT id, hash FROM audit ORDER BY id DESC LIMIT 1").fetchone()
            rid = 0 if last is None else int(last[0])
            prev = GENESIS if last is None or last[1] is None else last[1]
            for row in rows:
                rid += 1
                h = row_hash(prev, (rid, *row))
                db.execute(f"INSERT INTO audit ({_COLS}, prev_hash, hash) VALUES (?,?,?,?,?,?,?,?,?,?,?,?)",
                           (rid, *row, prev, h))
                prev = h
            db.execute("COMMIT")
            return True
        except BaseException:
            try:
                db.execute("ROLLBACK")
            except sqlite3.Error:
                pass
            raise

    def _ingest_spills(self) -> int:
        """Copy delayed rows from spill files into the database (idempotent: a summary row holds
        each file's hash), then rename the file ``audit.spill-ingested-<UTC>.jsonl``. Returns how
        many rows were copied in."""
        total = 0
        tmp_spill = Path(tempfile.gettempdir()) / f"monotracker-audit-spill-{self.session_id}.jsonl"
        for path in dict.fromkeys((self.path.with_name("audit.spill.jsonl"), tmp_spill)):
            if not path.is_file():
                continue
            try:
                raw = path.read_bytes()
                sha = hashlib.sha256(raw).hexdigest()
                rows, bad = [], 0
                keys = _COLS.split(", ")[1:]
                for line in raw.decode("utf-8", errors="replace").splitlines():
                    try:
                        d = json.loads(line)
                        rows.append(tuple(d[k] for k in keys))
                    except (ValueError, KeyError, TypeError):
                        bad += 1
                t = time.time()
                summary = (t, datetime.fromtimestamp(t, tz=timezone.utc).isoformat(timespec="milliseconds"), None,
                           self.session_id, "event", "info", "audit_spill_ingested",
                           f"{len(rows)} delayed rows copied in from {path.name}" + (f" ({bad} unreadable lines)" if bad else ""),
                           json.dumps({"file": str(path), "sha256": sha, "rows": len(rows), "unreadable": bad}))
                if self._insert(rows + [summary], check_sha=sha):
                    total += len(rows)
                stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
                os.replace(path, path.with_name(f"audit.spill-ingested-{stamp}-{sha[:8]}.jsonl"))
            except (OSError, sqlite3.Error) as exc:
                log.warning("delayed audit rows in %s not copied in yet: %s", path, exc)
        return total

    def _spill(self, rows: list, why: str) -> None:
        """Append rows to the spill file (JSON lines); count them delayed, or lost if that fails too."""
        text = "".join(json.dumps(dict(zip(_COLS.split(", ")[1:], r)), default=str) + "\n" for r in rows)
        for target in (self.spill_path, Path(tempfile.gettempdir()) / f"monotracker-audit-spill-{self.session_id}.jsonl"):
            try:
                with open(target, "a", encoding="utf-8") as fh:
                    fh.write(text)
                    fh.flush()
                    os.fsync(fh.fileno())
                self.spill_path = target
                with self._cond:
                    self.delayed += len(rows)
                self._alarm_delayed(why)
                return
            except OSError:
                continue
        with self._cond:
            self.lost += len(rows)
        self._alarm_delayed(why)

    def _alarm_delayed(self, why: str) -> None:
        now = time.monotonic()
        if self._trouble and now - self._last_alarm < 10.0:
            return  # one alarm per episode, then a count every 10 s
        self._trouble, self._last_alarm = True, now
        lost = f", {self.lost} lost" if self.lost else ""
        self._problem("alarm", "audit_lost" if self.lost else "audit_delayed",
                      f"audit log: {why}; {self.delayed} rows delayed to {self.spill_path}{lost}",
                      {"delayed": self.delayed, "lost": self.lost, "spill_file": str(self.spill_path)})

    def _problem(self, level: str, code: str, message: str, data: dict) -> None:
        log.warning("%s", message)
        cb = self.on_problem
        if cb is not None:
            try:
                cb(level, code, message, data)
            except Exception:  # noqa: BLE001
                log.exception("audit problem callback failed")

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until every queued row is written or spilled (at most ``timeout`` s); True if so."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._pending > 0:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    # ------------------------------------------------------------------ reading
    def entries(self, code: str | None = None, kind: str | None = None, session_id: str | None = None,
                limit: int | None = None) -> list[AuditEntry]:
        """Rows in the database, oldest first, optionally filtered; ``limit`` keeps the newest
        ``limit``. Waits (bounded) for queued rows first; spilled rows are not included."""
        self.flush()
        where, args = [], []
        for col, val in (("code", code), ("kind", kind), ("session_id", session_id)):
            if val is not None:
                where.append(f"{col} = ?")
                args.append(val)
        sql = f"SELECT {_COLS} FROM audit"
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY id DESC"
        if limit is not None:
            sql += f" LIMIT {int(limit)}"
        with self._read_lock:
            try:
                if self._reader is None:
                    self._reader = sqlite3.connect(str(self.path), check_same_thread=False, timeout=self.busy_timeout_s)
                rows = self._reader.execute(sql, args).fetchall()
            except sqlite3.Error as exc:
                log.warning("audit log not readable: %s", exc)
                return []
        return [AuditEntry(*r[:9], json.loads(r[9])) for r in reversed(rows)]

    def close(self, timeout: float = 5.0) -> None:
        """Write what is queued (at most ``timeout`` s), stop the writer, close the database."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
        self._q.put(None)
        self._thread.join(timeout)
        with self._read_lock:
            for db in (self._db, self._reader):
                if db is not None:
                    try:
                        db.close()
                    except sqlite3.Error:
                        pass
            self._db = self._reader = None


@dataclass(frozen=True)
class VerifyResult:
    """``ok``; ``rows`` checked; ``legacy`` rows from before the chain; ``first_bad_id`` (None
    when ok); ``reason`` one line; ``spilled`` rows waiting in spill files beside the database."""

    ok: bool
    rows: int
    legacy: int
    first_bad_id: int | None
    reason: str
    spilled: int = 0


def verify(path) -> VerifyResult:
    """Check the audit database at ``path``: protective triggers present, ids consecutive, every
    row's hash chained to the previous one, the ``robot_state`` rows following each other
    (``engine/audit_states.py``). Opens it read-only; never modifies it."""
    path = Path(path)
    if not path.is_file():
        return VerifyResult(False, 0, 0, None, f"no audit database at {path}")
    spilled = 0
    spill = path.with_name("audit.spill.jsonl")
    if spill.is_file():
        with open(spill, encoding="utf-8", errors="replace") as fh:
            spilled = sum(1 for line in fh if line.strip())
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5.0)
    except sqlite3.Error as exc:
        return VerifyResult(False, 0, 0, None, f"cannot open {path}: {exc}", spilled)
    try:
        names = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='trigger'")}
        missing = [t for t in TRIGGERS if t not in names]
        cols = {r[1] for r in db.execute("PRAGMA table_info(audit)")}
        if not {"hash", "prev_hash"} <= cols:
            return VerifyResult(False, 0, 0, None, "the audit table has no hash chain (written by an older version)", spilled)
        prev, expect_id, n, legacy, chained = GENESIS, None, 0, 0, False
        for r in db.execute(f"SELECT {_COLS}, prev_hash, hash FROM audit ORDER BY id"):
            n += 1
            rid, row, prev_hash, h = r[0], r[:10], r[10], r[11]
            if expect_id is not None and rid != expect_id:
                return VerifyResult(False, n, legacy, expect_id,
                                    f"row {expect_id} is missing (next row is {rid}): rows were deleted", spilled)
            expect_id = rid + 1
            if h is None and not chained:
                legacy += 1
                continue
            if h is None:
                return VerifyResult(False, n, legacy, rid, f"row {rid} has no hash inside the chain", spilled)
            if not chained:
                chained = True
                if prev_hash != GENESIS and legacy == 0:
                    return VerifyResult(False, n, legacy, rid, f"row {rid} chains to a row that is not there", spilled)
                prev = prev_hash if legacy else GENESIS
            if prev_hash != prev:
                return VerifyResult(False, n, legacy, rid,
                                    f"row {rid} does not chain to the row before it: a row was changed or removed", spilled)
            if row_hash(prev, row) != h:
                return VerifyResult(False, n, legacy, rid, f"row {rid} was changed after it was written (hash differs)",
                                    spilled)
            prev = h
        if missing:
            return VerifyResult(False, n, legacy, None, f"protective trigger(s) removed: {', '.join(missing)}", spilled)
        from monotracker.engine.audit_states import state_rows_problem

        bad = state_rows_problem(db)  # the robot_state rows follow each other
        if bad is not None:
            return VerifyResult(False, n, legacy, bad[0], bad[1], spilled)
        note = f"; {legacy} older rows before the chain began are not covered" if legacy else ""
        note += f"; {spilled} rows wait in {spill.name}" if spilled else ""
        return VerifyResult(True, n, legacy, None, f"{n} rows, hash chain intact, triggers present, robot state "
                                                   f"rows follow each other{note}", spilled)
    except sqlite3.Error as exc:
        return VerifyResult(False, 0, 0, None, f"cannot read {path}: {exc}", spilled)
    finally:
        db.close()


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
