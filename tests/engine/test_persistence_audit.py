"""Plan file (atomic), audit log (append-only), restart restores the plan and starts disarmed."""

import json
import os
import sqlite3

import numpy as np
import pytest

from monotracker.engine.audit import AuditLog
from monotracker.engine.persistence import atomic_write_json
from monotracker.engine.plan import Plan
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
                K=np.eye(3), dist=np.zeros(5), image_size=(1280, 720), T_base_cam=np.eye(4), camera_source="sim")
    plan.save(tmp_path / "p.json")
    back = Plan.load(tmp_path / "p.json")
    assert np.array_equal(back.fiducial_centres(), plan.fiducial_centres())
    assert np.array_equal(back.entry_lps_mm, plan.entry_lps_mm) and np.array_equal(back.target_lps_mm, plan.target_lps_mm)
    assert back.image_size == (1280, 720) and back.fiducials_locked


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
