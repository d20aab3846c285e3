"""The audit log's rows carry this machine's MAC and its end is anchored (issue 36). The
attacker here edits files the way a text editor or a script would: audit rows appended with
recomputed chain hashes, rows deleted from the end, forged spill lines, the database emptied. They do not have this machine's integrity key (kept outside
the session folder; ``docs/integrity.md`` says what someone who has it can still do)."""

import json
import os
import sqlite3
from pathlib import Path


from monotracker.engine.audit import GENESIS, AuditLog, row_hash, verify

from .conftest import restart as _restart
from .conftest import saved_plan as _saved

ROOT = Path(__file__).resolve().parents[2]


def _log(path, n=6):
    log = AuditLog(path, "s1")
    for i in range(n):
        log.record("event", "info", f"c{i}", f"row {i}", {"i": i})
    assert log.flush(30)
    log.close()


def _rechain(path, from_id, message):
    """Rewrite row ``from_id``'s message and recompute every hash from there (triggers dropped)."""
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("DROP TRIGGER audit_no_update")
    cols = "id, t_unix, t_iso, t_session, session_id, kind, level, code, message, data"
    rows = db.execute(f"SELECT {cols}, prev_hash FROM audit ORDER BY id").fetchall()
    prev = GENESIS
    for r in rows:
        row = list(r[:10])
        if row[0] == from_id:
            row[8] = message
        if row[0] >= from_id:
            h = row_hash(prev, tuple(row))
            db.execute("UPDATE audit SET message = ?, prev_hash = ?, hash = ? WHERE id = ?", (row[8], prev, h, row[0]))
            prev = h
        else:
            prev = db.execute("SELECT hash FROM audit WHERE id = ?", (row[0],)).fetchone()[0]
    db.execute("CREATE TRIGGER audit_no_update BEFORE UPDATE ON audit BEGIN SELECT RAISE(ABORT, 'x'); END;")
    db.close()


def test_a_chain_rewritten_with_recomputed_hashes_does_not_verify(tmp_path):
    p = tmp_path / "audit.sqlite"
    _log(p)
    assert verify(p).ok
    _rechain(p, 3, "forged")
    v = verify(p)
    assert not v.ok and v.first_bad_id == 3 and "MAC" in v.reason, v


def test_a_row_appended_with_a_recomputed_hash_does_not_verify(tmp_path):
    p = tmp_path / "audit.sqlite"
    _log(p)
    db = sqlite3.connect(p, isolation_level=None)
    rid, prev = db.execute("SELECT id, hash FROM audit ORDER BY id DESC LIMIT 1").fetchone()
    row = (rid + 1, 1.0, "x", None, "s", "alert", "info", "forged", "copied in from a spill file", "{}")
    db.execute("INSERT INTO audit (id, t_unix, t_iso, t_session, session_id, kind, level, code, message, data, "
               "prev_hash, hash) VALUES (?,?,?,?,?,?,?,?,?,?,?,?)", (*row, prev, row_hash(prev, row)))
    db.close()
    v = verify(p)
    assert not v.ok and v.first_bad_id == rid + 1 and "no MAC" in v.reason, v


def test_forged_lines_in_a_spill_file_are_never_copied_into_the_chain(tmp_path):
    p = tmp_path / "audit.sqlite"
    _log(p)
    forged = {"t_unix": 1.0, "t_iso": "x", "t_session": None, "session_id": "old", "kind": "event",
              "level": "info", "code": "forged_row", "message": "never happened", "data": "{}"}
    (tmp_path / "audit.spill.jsonl").write_text(json.dumps(forged) + "\n" + json.dumps(dict(forged, mac="0" * 64))
                                                + "\n")
    log = AuditLog(p, "s2")
    try:
        codes = [e.code for e in log.entries()]
    finally:
        log.close()
    assert "forged_row" not in codes and "audit_spill_refused" in codes
    assert verify(p).ok  # the chain holds only rows the app wrote (one of them says what was refused)


def test_rows_deleted_from_the_end_are_seen(tmp_path):
    p = tmp_path / "audit.sqlite"
    _log(p, 8)
    db = sqlite3.connect(p, isolation_level=None)
    db.execute("DROP TRIGGER audit_no_delete")
    db.execute("DELETE FROM audit WHERE id > 6")
    db.execute("CREATE TRIGGER audit_no_delete BEFORE DELETE ON audit BEGIN SELECT RAISE(ABORT, 'x'); END;")
    db.close()
    v = verify(p)
    assert not v.ok and "deleted from the end" in v.reason and "7..8" in v.reason, v
    # a session opening it says so, and the record of it outlives the anchor's next update
    log = AuditLog(p, "s2")
    assert log.tampered and "deleted from the end" in log.tampered
    log.record("event", "info", "later", "a later row")
    assert log.flush(30)
    log.close()
    v = verify(p)
    assert not v.ok and "records tampering" in v.reason and "deleted from the end" in v.reason, v


def test_an_emptied_audit_database_is_named_and_the_next_session_says_so(tmp_path):
    home = tmp_path / "home"
    _saved(home)
    with open(home / "audit.sqlite", "r+b") as fh:
        fh.truncate(0)
    for suffix in ("-wal", "-shm"):
        Path(str(home / "audit.sqlite") + suffix).unlink(missing_ok=True)
    v = verify(home / "audit.sqlite")
    assert not v.ok and "empty (0 bytes)" in v.reason and "erased" in v.reason and "older version" not in v.reason
    s = _restart(home)
    try:
        assert "audit_tampered" in [a.code for a in s.snapshot().alarms]
        assert "erased" in [a for a in s.snapshot().alarms if a.code == "audit_tampered"][0].message
    finally:
        s.shutdown()
    v = verify(home / "audit.sqlite")
    assert not v.ok and "records tampering" in v.reason


def test_spilled_rows_from_an_unwritable_home_are_merged_back_by_a_later_session(tmp_path):
    """The database cannot be opened and the folder refuses the spill file: the rows go to the
    temp folder, named after the database, where the next session (another id) finds them."""
    p = tmp_path / "audit.sqlite"
    _log(p, 2)
    os.rename(p, tmp_path / "moved.sqlite")
    p.mkdir()  # the database path cannot be opened
    (tmp_path / "audit.spill.jsonl").mkdir()  # nor can the spill file beside it
    log = AuditLog(p, "during")
    try:
        log.record("alert", "alarm", "estop", "EMERGENCY STOP")
        assert log.flush(30) and log.delayed == 1 and log.lost == 0
        assert log.spill_path.parent != tmp_path  # in the temp folder
    finally:
        log.close()
    p.rmdir()
    (tmp_path / "audit.spill.jsonl").rmdir()
    os.rename(tmp_path / "moved.sqlite", p)
    log = AuditLog(p, "after")  # a later session, another id
    try:
        codes = [e.code for e in log.entries()]
    finally:
        log.close()
    assert "estop" in codes and "audit_spill_ingested" in codes
    assert verify(p).ok
