"""The audit log tells the truth about the robot's state (issue 34): every ``robot_state`` row
carries the reason of the transition it records (not the one before), the rows follow each
other, and ``monotracker audit verify`` checks that they do.

The truth the rows are checked against is the robot's own: the safety layer's history of the
in-process tracker (simulated clock), and for the control process (real clock) the reasons the
safety layer gives each kind of transition (``robot/safety.py``)."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from monotracker.engine.audit import verify

from .conftest import plan_sample

ROOT = Path(__file__).resolve().parents[2]
T_STATE = 120.0


def robot_state_rows(s):
    """This session's robot_state rows, oldest first."""
    return [r for r in s.audit_entries(code="robot_state") if r.session_id == s.session_id]


def _advance_until(s, pred, what, dt=0.05, limit_s=60.0):
    t = 0.0
    while not pred():
        assert t < limit_s, f"timed out (simulated {limit_s} s) waiting for {what}"
        s.advance(dt)
        t += dt


def test_each_robot_state_row_carries_its_own_transition_in_order(make_session):
    """Arm / track / hold / STOP / reset on the simulated clock: the robot_state rows are the
    tracker's own transitions, one for one, each with its own reason."""
    s = make_session(clock="sim", camera="sim-points", trajectory="breathing", robot="sim", arm_pin="2468")
    plan_sample(s)
    assert s.start_camera().ok
    _advance_until(s, lambda: s.snapshot().pose is not None and s.snapshot().pose.trusted, "a trusted pose")
    assert s.arm("2468").ok
    s.advance(0.1)
    assert s.start_tracking().ok
    _advance_until(s, lambda: s.snapshot().robot.state == "tracking", "tracking")
    s.advance(0.3)
    assert s.inject_fault("occlude-all").ok  # the pose is lost: the arm holds
    _advance_until(s, lambda: s.snapshot().robot.state == "holding", "holding on occlusion")
    assert s.estop().ok
    s.advance(0.1)
    assert s.reset_estop().ok
    s.advance(0.1)
    assert s.snapshot().robot.state == "disarmed"

    truth = [(t.from_state.value, t.to_state.value, t.reason) for t in s._loop.robot.rig.tracker.safety.history]
    rows = robot_state_rows(s)
    got = [(r.data["from"], r.data["to"], r.data["reason"]) for r in rows]
    assert got == truth
    # and the message a reader sees names that same transition
    for r, (frm, to, why) in zip(rows, truth):
        assert r.message == f"robot {frm} -> {to} ({why})"
    kinds = [(f, t) for f, t, _ in truth]
    for step in (("disarmed", "armed"), ("armed", "tracking"), ("tracking", "holding"), ("holding", "estopped"),
                 ("estopped", "disarmed")):
        assert step in kinds
    s.shutdown()
    r = verify(Path(s.home) / "audit.sqlite")
    assert r.ok, r.reason
    assert "robot state rows follow each other" in r.reason


#: the safety layer's reason for each kind of operator transition (robot/safety.py); holds and
#: resumes give their cause, which is not an operator's word
OPERATOR_REASONS = {("disarmed", "armed"): "operator armed", ("armed", "tracking"): "operator started tracking",
                    ("holding", "estopped"): "operator e-stop", ("tracking", "estopped"): "operator e-stop",
                    ("estopped", "disarmed"): "operator reset the e-stop"}


@pytest.mark.serial  # the engine on the real clock: the serial lane (tests/conftest.py)
def test_control_process_rows_follow_each_other_with_their_own_reasons(make_session):
    """Real clock, the robot in its control process (where the state in shared memory runs
    ahead of the report explaining it): arm / track / hold / STOP / reset."""
    s = make_session(clock="real", camera="sim-points", trajectory="still", robot="sim", arm_pin="2468",
                     max_pose_age_s=5.0, freeze_after_s=5.0, start_wait_s=5.0)
    plan_sample(s)
    s.start()

    def wait(pred, what):
        t0 = time.monotonic()
        while not pred():
            assert time.monotonic() - t0 < T_STATE, f"timed out waiting for {what}"
            time.sleep(0.02)

    assert s.start_camera().ok
    wait(lambda: s.snapshot().pose is not None and s.snapshot().pose.trusted, "a trusted pose")
    wait(lambda: s.arm("2468").ok, "arming")
    wait(lambda: s.start_tracking().ok or s.snapshot().robot.state in ("tracking", "holding"), "tracking")
    assert s.inject_fault("occlude-all").ok
    wait(lambda: s.snapshot().robot.state == "holding", "holding on occlusion")
    assert s.estop().ok
    assert s.snapshot().robot.state == "estopped"  # what the control process acknowledged
    assert s.reset_estop().ok
    wait(lambda: s.snapshot().robot.state == "disarmed", "disarmed after the reset")
    wait(lambda: len(robot_state_rows(s)) >= 5 and robot_state_rows(s)[-1].data["to"] == "disarmed",
         "the rows of every transition")
    rows = robot_state_rows(s)
    prev = "disarmed"
    for r in rows:
        d = r.data
        assert d["from"] == prev, f"row {r.id} goes from {d['from']}, the row before went to {prev}"
        prev = d["to"]
        want = OPERATOR_REASONS.get((d["from"], d["to"]))
        if want is not None:
            assert d["reason"] == want, f"row {r.id} ({d['from']} -> {d['to']}) says {d['reason']!r}"
        if d["to"] == "holding":
            assert "operator" not in d["reason"], f"a hold with an operator's reason: {d['reason']!r}"
        assert r.message.endswith(f"({d['reason']})")
    seen = [(r.data["from"], r.data["to"]) for r in rows]
    assert ("holding", "estopped") in seen and ("estopped", "disarmed") in seen and ("disarmed", "armed") in seen
    s.shutdown()
    assert verify(Path(s.home) / "audit.sqlite").ok


def test_verify_names_the_first_state_row_that_does_not_follow(tmp_path):
    """A state row whose ``from`` is not where the row before went (a lost or reordered row, or
    a state polled instead of the transition): ``audit verify`` fails naming it, in one line."""
    from monotracker.engine.audit import AuditLog

    path = tmp_path / "audit.sqlite"
    log = AuditLog(path, "s1")
    chain = [("disarmed", "armed"), ("armed", "tracking"), ("holding", "estopped"), ("estopped", "disarmed")]
    for frm, to in chain:
        log.record("event", "info", "robot_state", f"robot {frm} -> {to}", {"from": frm, "to": to})
    log.close()
    r = verify(path)
    assert not r.ok
    db = sqlite3.connect(path)
    bad_id = db.execute("SELECT id FROM audit WHERE code='robot_state' AND data LIKE '%\"from\": \"holding\"%'").fetchone()[0]
    db.close()
    assert r.first_bad_id == bad_id
    assert "goes from holding" in r.reason and "went to tracking" in r.reason and "\n" not in r.reason
    # the command line says the same in one line, exit 1
    p = subprocess.run([sys.executable, "-m", "monotracker", "audit", "verify", str(tmp_path)], capture_output=True,
                       text=True, cwd=ROOT, env={"PYTHONPATH": str(ROOT / "app"), "PATH": "/usr/bin:/bin",
                            "MONOTRACKER_KEY_DIR": os.environ["MONOTRACKER_KEY_DIR"]})  # the key the rows were MACed with
    assert p.returncode == 1, p.stdout + p.stderr
    assert "goes from holding" in (p.stdout + p.stderr) and "Traceback" not in p.stderr


def test_verify_accepts_sessions_that_each_start_disarmed(tmp_path):
    """Each session starts disarmed (also after a crash mid-tracking): a new session's first
    row goes from disarmed, whatever the last session's last row said."""
    from monotracker.engine.audit import AuditLog

    path = tmp_path / "audit.sqlite"
    for sid, chain in (("s1", [("disarmed", "armed"), ("armed", "tracking")]),
                       ("s2", [("disarmed", "armed"), ("armed", "disarmed")])):
        log = AuditLog(path, sid)
        for frm, to in chain:
            log.record("event", "info", "robot_state", f"robot {frm} -> {to}", {"from": frm, "to": to})
        log.close()
    assert verify(path).ok
    log = AuditLog(path, "s3")
    log.record("event", "info", "robot_state", "robot armed -> tracking", {"from": "armed", "to": "tracking"})
    log.close()
    r = verify(path)
    assert not r.ok and "a session starts disarmed" in r.reason


def test_transition_reports_come_back_in_the_order_the_safety_layer_numbered_them():
    """Two threads' transitions reported in swapped order, one report lost, and a change the
    engine decides itself: handed on in order, the gap said, the chain unbroken."""
    from monotracker.engine.robot_transitions import TransitionLog

    now = [0.0]
    log = TransitionLog(gap_timeout_s=2.0, clock=lambda: now[0])
    log.add("tracking", "holding", "pose lost", 1.0, 2)  # arrives before #1
    assert log.drain() == []
    log.add("armed", "tracking", "operator started tracking", 0.5, 1)
    assert [(t.from_state, t.to_state) for t in log.drain()] == [("armed", "tracking"), ("tracking", "holding")]
    log.add("estopped", "disarmed", "operator reset the e-stop", 3.0, 4)  # #3 never comes
    assert log.drain() == []
    now[0] = 2.5
    got = log.drain()
    assert len(got) == 1 and "1 earlier transition report(s) lost" in got[0].reason
    log.add_local("estopped", "robot control process exited (killed)")
    got = log.drain()
    assert [(t.from_state, t.to_state, t.seq) for t in got] == [("disarmed", "estopped", None)]
    log.add("disarmed", "armed", "operator armed", 4.0, 4)  # a duplicate number: already handed on
    assert log.drain() == []
