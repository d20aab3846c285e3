"""Append-only, tamper-evident audit log in SQLite, written off the safety path.

Every decision and event of a session (fiducials confirmed or rejected, plan changes,
registrations, arm/disarm, tracking start/stop, alerts, faults, restarts) is one row with its
wall-clock time (Unix s and ISO-8601 UTC), the session clock, and JSON details.

Never blocks safety: :meth:`AuditLog.record` only puts the row on a bounded queue; a writer
thread of its own commits it. A stop, hold or alarm never waits on the database. When the
database is locked by another process, full, read-only or cannot be opened, rows go to a
JSON-lines spill file beside it (``audit.spill.jsonl``; if the folder is not writable or full, one
in the system's temp folder named after the database, so that a later session finds it); once the
database takes writes again (or when the next session opens it) the spilled rows are copied into
the chain, with an ``audit_spill_ingested`` row holding
the spill file's hash (so a crash in between cannot copy them twice), and the file is renamed
``audit.spill-ingested-*.jsonl``. ``on_problem(level, code, message, data)`` is told how many rows are
delayed (spilled) or lost (the queue overflowed or even the spill failed): the session raises that
as an ``audit_delayed`` / ``audit_lost`` alarm. :meth:`AuditLog.flush` waits (bounded) until the
queue is written, for readers that want every row so far. :meth:`AuditLog.record_durable` queues a
row and waits (bounded) until it is committed or spilled with ``fsync``: the plan's save writes
its ``plan_saved`` row this way *before* the file, so no saved plan lacks its row after ``kill -9``.

Tamper evidence: each row carries ``hash = sha256(prev_hash + canonical row)``, chained to the
previous row's hash (the first row chains to 64 zeros), and ``mac = HMAC(key, hash)`` with this
machine's integrity key (:class:`~monotracker.engine.integrity.IntegrityKey`, kept outside the
session folder). Triggers abort ``UPDATE``, ``DELETE`` and an ``INSERT`` (``OR REPLACE``) over an
existing id. After every write the log's *anchor* (its newest row's id and hash, MAC'd) is stored
in the key folder; at open and in :func:`verify` the database must still hold that row with that
hash, so rows deleted from the end, an erased or replaced file and a chain rewritten with
recomputed hashes are named (an ``audit_tampered`` row records what the next session found, so
the evidence outlives the anchor's update). Spilled lines carry a MAC too; a line without a valid
one (not written by this app on this machine) is never copied into the chain
(``audit_spill_refused``). :func:`verify` (``monotracker audit verify``) recomputes the chain,
the MACs and the anchor, checks the ids are consecutive and the triggers present, and names the
first bad row. Limits (``docs/integrity.md``): someone who can read the key (the same OS user,
or root) can forge everything; a log moved to another machine verifies only with its key.

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
from monotracker.engine.integrity import IntegrityKey

log = logging.getLogger(__name__)

GENESIS = "0" * 64
TRIGGERS = ("audit_no_update", "audit_no_delete", "audit_no_replace")
_DEFAULT_KEY = object()
#: the columns a row's chain and MAC add (older databases get them with ALTER TABLE)
_CHAIN_COLS = ("prev_hash", "hash", "mac")
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


def _line_body(d: dict) -> str:
    """The canonical text a spilled line's MAC covers (the line's fields without ``mac``)."""
    return json.dumps({k: v for k, v in d.items() if k != "mac"}, sort_keys=True, separators=(",", ":"), default=str)


def spill_glob_name(audit_path: Path) -> str:
    """The temp-folder spill files of the database at ``audit_path``: named after its absolute
    path, so that any later session of that folder finds them (``<prefix>-<session>.jsonl``)."""
    tag = hashlib.sha256(str(Path(audit_path).resolve()).encode("utf-8")).hexdigest()[:12]
    return f"monotracker-audit-spill-{tag}"


def _open_db(path: Path, timeout_s: float) -> sqlite3.Connection:
    db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None, timeout=timeout_s)
    try:
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=FULL")
        db.executescript(_SCHEMA)
        cols = {r[1] for r in db.execute("PRAGMA table_info(audit)")}
        for c in _CHAIN_COLS:
            if c not in cols:  # an audit log from before the chain / the MAC: its old rows stay without
                db.execute(f"ALTER TABLE audit ADD COLUMN {c} TEXT")
    except BaseException:
        db.close()
        raise
    return db


class AuditLog:
    """The audit database at ``path`` (created if missing). Thread-safe; never raises on write.

    ``on_problem(level, code, message, data)``: called from the writer thread when rows are
    delayed (spilled) or lost, and when the database works again. ``busy_timeout_s``: how long the
    writer waits for a locked database before it spills a batch. ``key``: this machine's
    :class:`~monotracker.engine.integrity.IntegrityKey` (default: the one in ``paths.key_dir()``,
    created if missing); None: rows carry no MAC and no anchor is kept. :attr:`tampered`: one line
    when the database at open did not match its anchor (an ``audit_tampered`` row records it)."""

    def __init__(self, path: Path, session_id: str, on_problem=None, queue_size: int = 10000,
                 busy_timeout_s: float = 0.5, key=_DEFAULT_KEY):
        self.path = Path(path)
        self.session_id = session_id
        self.key: IntegrityKey | None = IntegrityKey() if key is _DEFAULT_KEY else key
        self.spill_path = self.path.with_name("audit.spill.jsonl")
        self.tmp_spill_path = Path(tempfile.gettempdir()) / f"{spill_glob_name(self.path)}-{session_id}.jsonl"
        self.on_problem = on_problem
        self.busy_timeout_s = float(busy_timeout_s)
        self.delayed = 0  # rows written to a spill file instead of the database
        self.lost = 0  # rows neither in the database nor in a spill file
        self.refused = 0  # spilled lines without a valid MAC, never copied into the chain
        self.open_error: str | None = None
        self.tampered: str | None = None
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
        self._log_id: str | None = None  # the first chained row's hash (names the log in its anchor)
        self._outcome = "db"  # where the writer put its last batch: "db" | "spill" | "lost"
        self._deferred: list = []  # problem reports the writer thread makes after releasing waiters
        if self._try_open():
            self._check_anchor()
            self._ingest_checked = True
            self._ingest_spills()  # before anyone reads the log (the plan's restore does)
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

    def _check_anchor(self) -> None:
        """Compare the database with its anchor (the newest row the last writer recorded outside
        the file). A mismatch is recorded as an ``audit_tampered`` row and in :attr:`tampered`."""
        if self.key is None or not self.key.available:
            return
        try:
            db = self._db
            first = db.execute("SELECT hash FROM audit WHERE hash IS NOT NULL ORDER BY id LIMIT 1").fetchone()
            last = db.execute("SELECT id FROM audit ORDER BY id DESC LIMIT 1").fetchone()
        except sqlite3.Error as exc:
            log.warning("audit anchor not checked: %s", exc)
            return
        self._log_id = None if first is None else first[0]
        n = 0 if last is None else int(last[0])
        anchor, why = self.key.read_anchor(self.path, self._log_id)
        if why is None and anchor is not None:
            why = _anchor_mismatch(db, anchor, self._log_id, n)
        if why is None:
            return
        self.tampered = why
        log.error("audit log %s: %s", self.path, why)
        self.record("alert", "alarm", "audit_tampered", f"audit log {self.path.name}: {why}",
                    {"anchor": anchor, "rows_found": n})

    # ------------------------------------------------------------------ writing
    def _row(self, kind, level, code, message, data, t_unix, t_session) -> tuple:
        t = time.time() if t_unix is None else float(t_unix)
        iso = datetime.fromtimestamp(t, tz=timezone.utc).isoformat(timespec="milliseconds")
        try:
            payload = json.dumps(data or {}, default=_json_default, sort_keys=True)
        except (TypeError, ValueError) as exc:
            payload = json.dumps({"unserialisable": str(exc)})
        return (t, iso, t_session, self.session_id, kind, level, code, message, payload)

    def record(self, kind: str, level: str, code: str, message: str, data: dict | None = None,
               t_unix: float | None = None, t_session: float | None = None) -> None:
        """Queue one row (never blocks, never raises for a disk or database problem)."""
        self._enqueue(self._row(kind, level, code, message, data, t_unix, t_session), None)

    def record_durable(self, kind: str, level: str, code: str, message: str, data: dict | None = None,
                       timeout: float = 5.0) -> bool:
        """Queue one row and wait (at most ``timeout`` s) until it is committed to the database
        or written with ``fsync`` to a spill file; True if so, False if it was lost or the wait
        timed out (the row may still be written later). Rows queued before it are written first."""
        done = {"event": threading.Event(), "ok": False}
        self._enqueue(self._row(kind, level, code, message, data, None, None), done)
        return done["event"].wait(timeout) and bool(done["ok"])

    def _enqueue(self, row: tuple, done) -> None:
        with self._cond:
            if self._closed:
                self.lost += 1
                if done is not None:
                    done["event"].set()
                return
            self._pending += 1
        try:
            self._q.put_nowait((row, done))
        except queue.Full:
            with self._cond:
                self._pending -= 1
                self._cond.notify_all()
            ok = self._spill([row], "the audit queue is full")
            if done is not None:
                done["ok"] = ok
                done["event"].set()

    def record_event(self, ev: Event) -> None:
        """Sink for :class:`~monotracker.engine.events.EventBus` (non-blocking)."""
        self.record(ev.kind, ev.level, ev.code, ev.message, ev.data, t_unix=ev.t, t_session=ev.t_session)

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            batch = [item]
            while len(batch) < 256:
                try:
                    nxt = self._q.get_nowait()
                except queue.Empty:
                    break
                if nxt is None:
                    self._q.put(None)  # stop after this batch
                    break
                batch.append(nxt)
            rows = [r for r, _ in batch]
            try:
                self._write(rows)
            except Exception:  # the writer must survive anything
                log.exception("audit writer failed")
                self._spill(rows, "internal error in the audit writer")
            for _, done in batch:
                if done is not None:
                    done["ok"] = self._outcome != "lost"
                    done["event"].set()
            # alarms only now: a caller waiting in record_durable (holding its own locks) is
            # released first, whatever the alarm's subscribers do
            deferred, self._deferred = self._deferred, []
            for call in deferred:
                call()
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
        self._outcome = "db"
        if self._trouble or not self._ingest_checked:
            self._ingest_checked = True
            recovered = self._trouble
            self._trouble = False
            n = self._ingest_spills()
            if recovered:
                self._problem("info", "audit_recovered", f"audit database writable again; {n} delayed rows copied in",
                              {"delayed": self.delayed, "lost": self.lost, "ingested": n})

    def _insert(self, rows: list, check_sha: str | None = None) -> bool:
        """Append ``rows`` to the chain in one transaction, then update the anchor. With
        ``check_sha``: only if no ``audit_spill_ingested`` row names that spill file's hash yet
        (False: already in)."""
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
                mac = None if self.key is None else self.key.mac(h)
                db.execute(f"INSERT INTO audit ({_COLS}, prev_hash, hash, mac) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?)",
                           (rid, *row, prev, h, mac))
                prev = h
            db.execute("COMMIT")
        except BaseException:
            try:
                db.execute("ROLLBACK")
            except sqlite3.Error:
                pass
            raise
        if self._log_id is None:
            self._log_id = self._first_hash(db)
        self._write_anchor(rid, prev)
        return True

    @staticmethod
    def _first_hash(db) -> str | None:
        r = db.execute("SELECT hash FROM audit WHERE hash IS NOT NULL ORDER BY id LIMIT 1").fetchone()
        return None if r is None else r[0]

    def _write_anchor(self, last_id: int, last_hash: str) -> None:
        if self.key is None or not self.key.available or self._log_id is None:
            return
        try:
            self.key.write_anchor(self.path, self._log_id, last_id, last_hash)
        except OSError as exc:  # the chain is committed; only the protection of its end lags
            log.warning("audit anchor not updated (%s): the newest rows are not covered yet", exc)

    def _spill_files(self) -> list[Path]:
        """Spill files of this database: beside it, and in the temp folder (any session's)."""
        files = [self.path.with_name("audit.spill.jsonl")]
        try:
            files += sorted(Path(tempfile.gettempdir()).glob(f"{spill_glob_name(self.path)}-*.jsonl"))
        except OSError:
            pass
        return [p for p in dict.fromkeys(files) if p.is_file()]

    def _read_spill(self, raw: bytes) -> tuple[list[tuple], int, int]:
        """``(rows, unreadable lines, refused lines)`` of a spill file's bytes; a line whose MAC
        does not verify with this machine's key is refused (never copied into the chain)."""
        rows, bad, refused = [], 0, 0
        keys = _COLS.split(", ")[1:]
        for line in raw.decode("utf-8", errors="replace").splitlines():
            if not line.strip():
                continue
            try:
                d = json.loads(line)
                row = tuple(d[k] for k in keys)
            except (ValueError, KeyError, TypeError):
                bad += 1
                continue
            if self.key is not None and self.key.check(_line_body(d), d.get("mac")) is False:
                refused += 1
                continue
            rows.append(row)
        return rows, bad, refused

    def _ingest_spills(self) -> int:
        """Copy delayed rows from spill files into the database (idempotent: a summary row holds
        each file's hash), then rename the file ``audit.spill-ingested-<UTC>.jsonl`` (beside the
        database). Lines without a valid MAC are refused: an ``audit_spill_refused`` alarm row
        says how many. Returns how many rows were copied in."""
        total = 0
        for path in self._spill_files():
            try:
                raw = path.read_bytes()
                sha = hashlib.sha256(raw).hexdigest()
                rows, bad, refused = self._read_spill(raw)
                t = time.time()
                iso = datetime.fromtimestamp(t, tz=timezone.utc).isoformat(timespec="milliseconds")
                note = (f" ({bad} unreadable lines)" if bad else "") + (
                    f" ({refused} lines refused: no valid MAC, not written by this app on this machine)" if refused else "")
                summary = (t, iso, None, self.session_id, "event", "info", "audit_spill_ingested",
                           f"{len(rows)} delayed rows copied in from {path.name}{note}",
                           json.dumps({"file": str(path), "sha256": sha, "rows": len(rows), "unreadable": bad,
                                       "refused": refused}))
                extra = []
                if refused:
                    extra.append((t, iso, None, self.session_id, "alert", "alarm", "audit_spill_refused",
                                  f"{refused} lines of {path.name} were not copied into the audit log: they carry no "
                                  "valid MAC (forged, or written on another machine)",
                                  json.dumps({"file": str(path), "sha256": sha, "refused": refused})))
                if self._insert(rows + [summary] + extra, check_sha=sha):
                    total += len(rows)
                    with self._cond:
                        self.refused += refused
                stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
                dest = self.path.with_name(f"audit.spill-ingested-{stamp}-{sha[:8]}.jsonl")
                try:
                    os.replace(path, dest)
                except OSError:  # another file system (the temp folder): copy, then remove
                    import shutil

                    shutil.copyfile(path, dest)
                    path.unlink()
            except (OSError, sqlite3.Error) as exc:
                log.warning("delayed audit rows in %s not copied in yet: %s", path, exc)
        return total

    def _spill(self, rows: list, why: str) -> bool:
        """Append rows to the spill file (JSON lines with a MAC); count them delayed, or lost if
        that fails too. True when they are on disk."""
        keys = _COLS.split(", ")[1:]
        lines = []
        for r in rows:
            d = dict(zip(keys, r))
            if self.key is not None and self.key.available:
                d["mac"] = self.key.mac(_line_body(d))
            lines.append(json.dumps(d, default=str) + "\n")
        text = "".join(lines)
        for target in (self.spill_path, self.tmp_spill_path):
            try:
                with open(target, "a", encoding="utf-8") as fh:
                    fh.write(text)
                    fh.flush()
                    os.fsync(fh.fileno())
                self.spill_path = target
                with self._cond:
                    self.delayed += len(rows)
                self._outcome = "spill"
                self._alarm_delayed(why)
                return True
            except OSError:
                continue
        with self._cond:
            self.lost += len(rows)
        self._outcome = "lost"
        self._alarm_delayed(why)
        return False

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
        if threading.current_thread() is getattr(self, "_thread", None):
            self._deferred.append(lambda: self._report(level, code, message, data))
            return
        self._report(level, code, message, data)

    def _report(self, level: str, code: str, message: str, data: dict) -> None:
        log.warning("%s", message)
        cb = self.on_problem
        if cb is not None:
            try:
                cb(level, code, message, data)
            except Exception:
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
        rows = self._read(sql, args)
        return [AuditEntry(*r[:9], json.loads(r[9])) for r in reversed(rows)]

    def _read(self, sql: str, args=()) -> list:
        with self._read_lock:
            try:
                if self._reader is None:
                    self._reader = sqlite3.connect(str(self.path), check_same_thread=False, timeout=self.busy_timeout_s)
                return self._reader.execute(sql, args).fetchall()
            except sqlite3.Error as exc:
                log.warning("audit log not readable: %s", exc)
                return []

    def last_record(self, code: str) -> tuple[dict | None, str | None]:
        """The ``data`` of the newest row with ``code`` whose hash and MAC verify, from the
        database (or from the spill files while the database cannot be opened), and one line
        about the newer rows with that code that do not verify (changed after writing, or not
        written with this machine's key: forged), or None: ``(data or None, problem or None)``."""
        self.flush()
        problem = None
        for r in self._read(f"SELECT {_COLS}, prev_hash, hash, mac FROM audit WHERE code = ? ORDER BY id DESC "
                            "LIMIT 1000", (code,)):
            if r[11] is None or row_hash(r[10], r[:10]) != r[11]:
                problem = problem or f"the audit log's {code} row {r[0]} was changed after it was written"
                continue
            if self.key is not None and self.key.check(r[11], r[12]) is False:
                problem = problem or (f"the audit log's {code} row {r[0]} carries no valid MAC: it was not written "
                                      "by this app on this machine (forged)")
                continue
            return json.loads(r[9]), problem
        if self._db is not None:
            return None, problem
        newest = None  # the database cannot be opened: the rows went to spill files
        for path in self._spill_files():
            try:
                rows, _, _ = self._read_spill(path.read_bytes())
            except OSError:
                continue
            for row in rows:
                if row[6] == code and (newest is None or row[0] >= newest[0]):
                    newest = row
        return (None, None) if newest is None else (json.loads(newest[8]), None)

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


def _anchor_mismatch(db, anchor: dict, log_id: str | None, n_rows: int) -> str | None:
    """One line when the database ``db`` (``n_rows`` = its newest id, ``log_id`` its first
    chained row's hash) no longer holds the row its anchor recorded; None when it does."""
    want_id, want_hash = int(anchor.get("last_id", 0)), anchor.get("last_hash")
    if log_id is None:
        return (f"the audit log is empty, but its anchor records {want_id} rows: it was erased or replaced"
                if want_id > 0 else None)
    if anchor.get("log_id") != log_id:
        return (f"the audit log was replaced: its anchor records {want_id} rows of another log "
                f"(first row {str(anchor.get('log_id'))[:12]}..., this file's {log_id[:12]}...)")
    if n_rows < want_id:
        return (f"rows {n_rows + 1}..{want_id} were deleted from the end of the audit log "
                f"(its anchor records {want_id} rows, the file holds {n_rows})")
    r = db.execute("SELECT hash FROM audit WHERE id = ?", (want_id,)).fetchone()
    if r is None or r[0] != want_hash:
        return f"the audit log was rewritten: row {want_id} no longer has the hash its anchor records"
    return None


@dataclass(frozen=True)
class VerifyResult:
    """``ok``; ``rows`` checked; ``legacy`` rows from before the chain; ``first_bad_id`` (None
    when ok); ``reason`` one line; ``spilled`` rows waiting in spill files beside the database;
    ``anchored``: whether the log's end was checked against its anchor (this machine's key)."""

    ok: bool
    rows: int
    legacy: int
    first_bad_id: int | None
    reason: str
    spilled: int = 0
    anchored: bool = False


def verify(path, key=None) -> VerifyResult:
    """Check the audit database at ``path``: protective triggers present, ids consecutive, every
    row's hash chained to the previous one, the ``robot_state`` rows following each other
    (``engine/audit_states.py``), every row's MAC (``key``: an
    :class:`~monotracker.engine.integrity.IntegrityKey`; None = this machine's, never created
    here), the newest rows still those the anchor recorded, no ``audit_tampered`` row. Opens it
    read-only; never modifies it."""
    path = Path(path)
    if not path.is_file():
        return VerifyResult(False, 0, 0, None, f"no audit database at {path}")
    key = IntegrityKey(create=False) if key is None else key
    spilled = 0
    spill = path.with_name("audit.spill.jsonl")
    if spill.is_file():
        with open(spill, encoding="utf-8", errors="replace") as fh:
            spilled = sum(1 for line in fh if line.strip())
    anchor, anchor_why = key.read_anchor(path) if key.available else (None, None)

    def bad(reason, n=0, legacy=0, rid=None):
        return VerifyResult(False, n, legacy, rid, reason, spilled)

    if path.stat().st_size == 0:
        held = f" (its anchor records {anchor['last_id']} rows)" if anchor else ""
        return bad(f"{path.name} is empty (0 bytes): the audit log was erased{held}")
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5.0)
    except sqlite3.Error as exc:
        return bad(f"cannot open {path}: {exc}")
    try:
        names = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='trigger'")}
        missing = [t for t in TRIGGERS if t not in names]
        cols = {r[1] for r in db.execute("PRAGMA table_info(audit)")}
        if not cols:
            return bad(f"{path.name} holds no audit table: not a MonoTracker audit log, or its contents were removed")
        if not {"hash", "prev_hash"} <= cols:
            return bad("the audit table has no hash chain (written by a version of MonoTracker before the chain)")
        has_mac = "mac" in cols
        mac_sql = ", mac" if has_mac else ", NULL"
        prev, expect_id, n, legacy, chained, macs = GENESIS, None, 0, 0, False, 0
        first_hash, tamper_rows = None, []
        for r in db.execute(f"SELECT {_COLS}, prev_hash, hash{mac_sql} FROM audit ORDER BY id"):
            n += 1
            rid, row, prev_hash, h, mac = r[0], r[:10], r[10], r[11], r[12]
            if expect_id is not None and rid != expect_id:
                return bad(f"row {expect_id} is missing (next row is {rid}): rows were deleted", n, legacy, expect_id)
            expect_id = rid + 1
            if h is None and not chained:
                legacy += 1
                continue
            if h is None:
                return bad(f"row {rid} has no hash inside the chain", n, legacy, rid)
            if not chained:
                chained, first_hash = True, h
                if prev_hash != GENESIS and legacy == 0:
                    return bad(f"row {rid} chains to a row that is not there", n, legacy, rid)
                prev = prev_hash if legacy else GENESIS
            if prev_hash != prev:
                return bad(f"row {rid} does not chain to the row before it: a row was changed or removed",
                           n, legacy, rid)
            if row_hash(prev, row) != h:
                return bad(f"row {rid} was changed after it was written (hash differs)", n, legacy, rid)
            if mac is not None or macs:
                if not key.available:
                    return bad(f"rows carry MACs but there is no integrity key here ({key.problem}): verify on "
                               "the machine that wrote the log, or point MONOTRACKER_KEY_DIR at its key",
                               n, legacy, rid)
                if mac is None:
                    return bad(f"row {rid} carries no MAC although the rows before it do: it was not written by "
                               "this app (forged, e.g. copied in with a recomputed hash)", n, legacy, rid)
                if not key.check(h, mac):
                    return bad(f"row {rid}'s MAC does not verify: it was not written by this app with this "
                               "machine's key (forged, or the chain rewritten with recomputed hashes)", n, legacy, rid)
                macs += 1
            if row[7] == "audit_tampered":
                tamper_rows.append((rid, row[8]))
            prev = h
        if missing:
            return bad(f"protective trigger(s) removed: {', '.join(missing)}", n, legacy)
        from monotracker.engine.audit_states import state_rows_problem

        states_bad = state_rows_problem(db)  # the robot_state rows follow each other
        if states_bad is not None:
            return bad(states_bad[1], n, legacy, states_bad[0])
        if key.available:  # by this database's path, else (a moved folder) by the log's first hash
            anchor, anchor_why = key.read_anchor(path, first_hash)
        if anchor_why:
            return bad(anchor_why, n, legacy)
        if anchor is not None:
            why = _anchor_mismatch(db, anchor, first_hash, expect_id - 1 if expect_id else 0)
            if why:
                return bad(why, n, legacy)
        elif macs:
            return bad("the audit log's anchor on this machine is missing or belongs to another log: rows deleted "
                       "from its end, or an erased and rebuilt log, cannot be ruled out", n, legacy)
        if tamper_rows:
            rid, msg = tamper_rows[-1]
            return bad(f"row {rid} records tampering found when a session opened the log: {msg}", n, legacy, rid)
        note = f"; {legacy} older rows before the chain began are not covered" if legacy else ""
        if n and not macs:
            note += "; rows carry no MAC (written without an integrity key): a rewrite with recomputed hashes " \
                    "or rows deleted from the end would not be seen"
        note += f"; {spilled} rows wait in {spill.name}" if spilled else ""
        what = "hash chain, MACs and anchor intact" if macs else "hash chain intact"
        return VerifyResult(True, n, legacy, None, f"{n} rows, {what}, triggers present, robot state rows follow "
                            f"each other{note}", spilled, anchored=anchor is not None)
    except sqlite3.Error as exc:
        return bad(f"cannot read {path}: {exc}")
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
