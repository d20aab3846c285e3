"""Plan file (atomic), audit log (append-only), restart restores the plan and starts disarmed."""

import json
import os
import sqlite3

import numpy as np
import pytest
from pathlib import Path

from monotracker.engine.audit import AuditLog
from monotracker.engine.persistence import atomic_write_json
from monotracker.engine.plan import Plan, load_plan
from monotracker.sim.phantom import default_phantom

from .conftest import plan_sample


def test_atomic_write_keeps_old_file_when_the_rename_fails(tmp_path, monkeypatch):
    p = tmp_path / "plan.json"
    atomic_write_json(p, {"a": 1})

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        atomic_write_json(p, {"a": 2})
    assert json.loads(p.read_text()) == {"a": 1}
    assert [f.name for f in tmp_path.iterdir()] == ["plan.json"]  # no temp file left behind


def test_audit_log_is_append_only(tmp_path):
    log = AuditLog(tmp_path / "a.sqlite", "s1")
    log.record("event", "info", "x", "first", {"v": np.float64(1.5), "arr": np.arange(3)})
    log.record("alert", "alarm", "y", "second")
    assert log.flush(30)
    i = log.entries()[0].id
    db = sqlite3.connect(tmp_path / "a.sqlite")
    with pytest.raises(sqlite3.DatabaseError, match="append-only"):
        db.execute("UPDATE audit SET message='forged' WHERE id=?", (i,))
    with pytest.raises(sqlite3.DatabaseError, match="append-only"):
        db.execute("DELETE FROM audit")
    rows = log.entries()
    assert [r.code for r in rows] == ["x", "y"]
    assert rows[0].data == {"v": 1.5, "arr": [0, 1, 2]}
    assert rows[0].t_iso.endswith("+00:00")
    log.close()


def test_plan_round_trip_is_exact(tmp_path):
    ph = default_phantom()
    from monotracker.engine.plan import PlanFiducial

    plan = Plan(ct_path="/x/ct.nii.gz",
                fiducials=[PlanFiducial(i, c, 4.0, 0.9, "confirmed") for i, c in enumerate(ph.fiducial_centres_lps)],
                fiducials_locked=True, entry_lps_mm=ph.sample_entry_lps, target_lps_mm=ph.sample_target_lps,
                K=np.array([[1100.0, 0, 640.3], [0, 1098.5, 359.7], [0, 0, 1]]),
                dist=np.array([-0.12, 0.05, 1e-4, -2e-4, 0.0]), image_size=(1280, 720),
                T_base_cam=np.eye(4), camera_source="sim")
    plan.save(tmp_path / "p.json")
    back = load_plan(tmp_path / "p.json")
    assert np.array_equal(back.fiducial_centres(), plan.fiducial_centres())
    assert np.array_equal(back.entry_lps_mm, plan.entry_lps_mm) and np.array_equal(back.target_lps_mm, plan.target_lps_mm)
    assert back.image_size == (1280, 720) and back.fiducials_locked
    assert np.array_equal(back.K, plan.K) and np.array_equal(back.dist, plan.dist)


def test_restart_restores_plan_and_starts_disarmed(make_session):
    s = make_session(clock="sim")
    plan_sample(s)
    before = s.plan_copy().to_dict()
    s.shutdown()
    s2 = make_session(clock="sim")
    snap = s2.snapshot()
    assert s2.plan_copy().to_dict() == before
    assert snap.robot.state == "disarmed" and snap.fiducials_locked and snap.plan.complete
    codes = [e.code for e in s2.audit_entries()]
    assert codes.count("session_started") == 2 and "plan_restored" in codes and "fiducials_locked" in codes


def test_corrupt_plan_file_is_kept_aside_with_an_alarm(make_session, home):
    home.mkdir(parents=True)
    (home / "plan.json").write_text("{ not json")
    s = make_session(clock="sim")
    assert s.snapshot().fiducials == ()
    assert any(a.code == "plan_unreadable" for a in s.snapshot().alerts)
    assert any(p.name.startswith("plan.unreadable-") for p in home.iterdir())


# ---------------------------------------------------------------------------------------------
# Persistence failures refuse, they do not diverge (issue 17 item 3)
def _disk_full(monkeypatch):
    import errno

    from monotracker.engine import persistence

    real = persistence.os.replace

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(persistence.os, "replace", full)
    return lambda: monkeypatch.setattr(persistence.os, "replace", real)


def test_disk_full_refuses_commands_and_memory_stays_equal_to_disk(make_session, home, monkeypatch):
    s = make_session(clock="sim")
    ph = default_phantom()
    for c in ph.fiducial_centres_lps:
        assert s.add_fiducial(c, ph.fiducial_radius_mm).ok
    on_disk = json.loads((home / "plan.json").read_text())
    heal = _disk_full(monkeypatch)
    r = s.confirm_fiducials()
    assert not r.ok and "No space left on device" in r.message and "\n" not in r.message
    for f in s.snapshot().fiducials:
        r = s.set_fiducial_status(f.id, "rejected")
        assert not r.ok and "not saved" in r.message
    r = s.set_hand_eye(np.eye(4))
    assert not r.ok
    # memory is what is on disk: nothing unlocked, nothing rejected, no hand-eye
    assert s.plan_copy().to_dict() == on_disk == json.loads((home / "plan.json").read_text())
    assert not s.snapshot().fiducials_locked
    alarms = [a.code for a in s.snapshot().alerts]
    assert alarms.count("home_unwritable") == 1 and "plan_save_failed" in alarms
    assert [c for c, _ in s.integrity_alarms()] == ["home_unwritable"]  # stands while unwritable
    heal()
    assert s.confirm_fiducials().ok
    assert json.loads((home / "plan.json").read_text())["fiducials_locked"] is True
    assert "home_writable" in [a.code for a in s.snapshot().alerts] and s.integrity_alarms() == []
    s.shutdown()
    assert make_session(clock="sim").snapshot().fiducials_locked  # after a restart: what was said done


_RO_CHILD = r'''
import json, sys
from monotracker.engine import Session, SessionConfig
s = Session(SessionConfig(home=sys.argv[1], clock="sim"))
r = s.unlock_fiducials()
out = {"codes": [a.code for a in s.snapshot().alerts], "unlock": [r.ok, r.message],
       "locked": s.snapshot().fiducials_locked, "spill": str(s._audit.spill_path)}
s.shutdown()
print(json.dumps(out))
'''


def test_read_only_home_starts_with_a_clear_alarm(tmp_path):
    import shutil
    import subprocess
    import sys
    import tempfile

    from monotracker.engine import Session, SessionConfig

    # a folder the unprivileged child can reach (pytest's tmp_path is private to this user)
    home = Path(tempfile.mkdtemp(prefix="monotracker-ro-home-"))
    os.chmod(home, 0o755)
    try:
        _read_only_home_case(home, Session, SessionConfig, subprocess, sys)
    finally:
        os.chmod(home, 0o755)
        shutil.rmtree(home, ignore_errors=True)


def _read_only_home_case(home, Session, SessionConfig, subprocess, sys):
    s = Session(SessionConfig(home=home, clock="sim"))
    plan_sample(s)
    s.shutdown()
    before = (home / "plan.json").read_text()
    os.chmod(home, 0o555)
    for f in home.iterdir():
        os.chmod(f, 0o444)
    cmd = [sys.executable, "-c", _RO_CHILD, str(home)]
    if os.geteuid() == 0:  # root ignores folder modes: run the child as nobody
        import shutil

        if shutil.which("setpriv") is None:
            pytest.skip("running as root without setpriv: cannot make a folder read-only for the child")
        cmd = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"] + cmd
        probe = subprocess.run(cmd[:4] + [sys.executable, "-c", "import monotracker"], capture_output=True, cwd="/")
        if probe.returncode != 0:  # e.g. a checkout inside a private (0700) folder that nobody cannot enter
            os.chmod(home, 0o755)
            pytest.skip("the unprivileged child cannot import monotracker from this checkout (private folder)")
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd="/")
    finally:
        os.chmod(home, 0o755)
    assert p.returncode == 0, p.stderr[-2000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    assert "home_unwritable" in out["codes"] and "audit_unavailable" in out["codes"]
    ok, msg = out["unlock"]
    assert not ok and "not saved" in msg and out["locked"]  # refused, memory unchanged
    assert (home / "plan.json").read_text() == before
    spill = Path(out["spill"])
    assert spill.is_file() and "home_unwritable" in spill.read_text()  # the events were not lost
    spill.unlink()


# ---------------------------------------------------------------------------------------------
# The audit log never blocks safety (issue 17 item 4)
_LOCKER = r'''
import sqlite3, sys, time
db = sqlite3.connect(sys.argv[1], isolation_level=None)
db.execute("BEGIN EXCLUSIVE")
print("LOCKED", flush=True)
sys.stdin.readline()  # hold the lock until told
db.execute("COMMIT")
'''


def test_stop_does_not_wait_for_a_locked_audit_database(make_session, home):
    import subprocess
    import sys
    import time

    from .doubles import FollowerRobotRig, TruthCameraRig

    cam, rob = TruthCameraRig("still"), FollowerRobotRig()
    s = make_session(clock="sim", camera_factory=lambda *a: cam, robot_factory=lambda *a: rob)
    plan_sample(s)
    assert s.start_camera().ok
    s.advance(0.3)
    assert s.arm("1234").ok and s.start_tracking().ok
    s.advance(0.5)
    assert s._audit.flush(30)
    locker = subprocess.Popen([sys.executable, "-c", _LOCKER, str(home / "audit.sqlite")], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert locker.stdout.readline().strip() == "LOCKED"
        t0 = time.perf_counter()
        r = s.estop()
        took = time.perf_counter() - t0
        assert r.ok
        s.inject_fault("camera-freeze")  # more events while the database is locked
        # estop returned while the database was still locked by the other process: it did not wait on it
        assert locker.poll() is None
        assert took < 5.0  # generous: a blocked write would have taken the busy timeout per event
        assert s.snapshot().robot.state == "estopped"
        s.advance(0.2)
        assert np.max(np.abs(rob.status().qd)) < 1e-9  # the arm is still
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and "audit_delayed" not in [a.code for a in s.snapshot().alerts]:
            time.sleep(0.05)
        assert "audit_delayed" in [a.code for a in s.snapshot().alerts]
    finally:
        locker.communicate("go\n", timeout=30)
    # once the lock is gone the delayed rows are copied into the chain, once each, none lost
    s.alert("info", "after_lock", "a row after the lock is released")
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and "audit_spill_ingested" not in [e.code for e in s.audit_entries()]:
        time.sleep(0.05)
    db_codes = [e.code for e in s.audit_entries()]
    assert "audit_spill_ingested" in db_codes
    assert db_codes.count("estop") == 1 and db_codes.count("fault_injected") == 1, db_codes[-12:]
    assert s._audit.lost == 0 and s._audit.delayed >= 1
    assert not (home / "audit.spill.jsonl").exists() and list(home.glob("audit.spill-ingested-*.jsonl"))
    from monotracker.engine.audit import verify

    assert verify(home / "audit.sqlite").ok


# ---------------------------------------------------------------------------------------------
# Tamper-evident audit (issue 17 item 5)
def _filled_log(path):
    log = AuditLog(path, "s1")
    for i in range(6):
        log.record("event", "info", f"c{i}", f"row {i}", {"i": i})
    assert log.flush(30)
    log.close()


def _tamper(path, *sql):
    db = sqlite3.connect(path, isolation_level=None)
    for q in sql:
        db.execute(q)
    db.close()


def test_audit_verify_passes_an_untouched_log(tmp_path):
    from monotracker.engine.audit import verify

    p = tmp_path / "a.sqlite"
    _filled_log(p)
    v = verify(p)
    assert v.ok and v.rows == 6, v.reason


@pytest.mark.parametrize("sql,bad_id,word", [
    (["DROP TRIGGER audit_no_update", "UPDATE audit SET message='forged' WHERE id=3"], 3, "changed"),
    (["DROP TRIGGER audit_no_delete", "DELETE FROM audit WHERE id=3"], 3, "missing"),
    (["DROP TRIGGER audit_no_replace",
      "INSERT OR REPLACE INTO audit (id, t_unix, t_iso, session_id, kind, level, code, message, data, prev_hash, hash)"
      " SELECT id, t_unix, t_iso, session_id, kind, level, code, 'forged', data, prev_hash, hash FROM audit WHERE id=4"],
     4, "changed"),
    (["DROP TRIGGER audit_no_delete"], None, "trigger"),
])
def test_audit_verify_names_the_first_bad_row(tmp_path, sql, bad_id, word):
    from monotracker.engine.audit import verify

    p = tmp_path / "a.sqlite"
    _filled_log(p)
    _tamper(p, *sql)
    v = verify(p)
    assert not v.ok and v.first_bad_id == bad_id and word in v.reason, v


def test_insert_or_replace_is_refused_by_the_database(tmp_path):
    p = tmp_path / "a.sqlite"
    _filled_log(p)
    db = sqlite3.connect(p)
    with pytest.raises(sqlite3.DatabaseError, match="append-only"):
        db.execute("INSERT OR REPLACE INTO audit (id, t_unix, t_iso, session_id, kind, level, code, message, data)"
                   " VALUES (2, 0, '', 's', 'event', 'info', 'x', 'forged', '{}')")
    db.close()


def test_spilled_rows_are_copied_in_once(tmp_path):
    from monotracker.engine.audit import verify

    p = tmp_path / "audit.sqlite"
    _filled_log(p)
    from monotracker.engine.audit import _line_body
    from monotracker.engine.integrity import IntegrityKey

    spill = tmp_path / "audit.spill.jsonl"
    rows = [{"t_unix": 1.0 + i, "t_iso": "x", "t_session": None, "session_id": "old", "kind": "alert",
             "level": "alarm", "code": f"spilled{i}", "message": "m", "data": "{}"} for i in range(2)]
    key = IntegrityKey()  # as the app spills them: each line with this machine's MAC
    lines = "".join(json.dumps(dict(r, mac=key.mac(_line_body(r)))) + "\n" for r in rows)
    spill.write_text(lines)
    for _ in range(2):  # the second time: as if a crash came between the copy and the rename
        log = AuditLog(p, "s2")
        log.record("event", "info", "next", "a row")
        assert log.flush(30)
        codes = [e.code for e in log.entries()]
        log.close()
        assert codes.count("spilled0") == 1 and codes.count("spilled1") == 1 and not spill.exists()
        spill.write_text(lines)
    assert codes.count("audit_spill_ingested") == 1
    assert verify(p).ok
