"""kill -9 in the middle of tracking, then restart: the plan is intact and the arm disarmed."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from monotracker.engine import Session, SessionConfig

CHILD = Path(__file__).with_name("crash_child.py")
ROOT = Path(__file__).resolve().parents[2]


def test_kill_9_mid_tracking_then_restart(tmp_path):
    home = tmp_path / "home"
    env = dict(os.environ, PYTHONPATH=str(ROOT / "app"))
    args = [sys.executable, str(CHILD), str(home)]
    p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    try:
        line = p.stdout.readline()
        assert line.startswith("TRACKING "), (line, p.stderr.read() if p.poll() is not None else "")
        plan_at_tracking = json.loads(line[len("TRACKING "):])
        time.sleep(0.7)  # let it track (and write) for a while
        assert p.poll() is None, "child died on its own"
        os.kill(p.pid, signal.SIGKILL)
        p.wait(10)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == -signal.SIGKILL

    s = Session(SessionConfig(home=home, clock="sim"))
    try:
        snap = s.snapshot()
        assert s.plan_copy().to_dict() == plan_at_tracking
        assert snap.robot.state == "disarmed"
        assert snap.fiducials_locked and snap.plan.complete
        rows = s.audit_entries()
        child_rows = [r for r in rows if r.session_id != s.session_id]
        assert "tracking_started" in [r.code for r in child_rows]
        assert "session_shutdown" not in [r.code for r in child_rows]  # it really died
        assert [r.code for r in rows if r.session_id == s.session_id][:2] == ["plan_restored", "session_started"]
    finally:
        s.shutdown()
