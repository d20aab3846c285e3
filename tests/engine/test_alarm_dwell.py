"""Alarms with a meaning (issue 33 item 4): a late frame is not a frozen camera, and a condition
that flaps is one alarm, not one per flap. Simulated clocks throughout (no wall time).

The arm's hold is never part of this: a late or missing frame still holds it at once (the robot's
0.1 s freshness rule); only what the board shows and the audit reports changes."""

import numpy as np
import pytest

from monotracker.engine.alarms import CATALOGUE, AlarmBoard

from .conftest import plan_sample
from .doubles import FakeFrame, FollowerRobotRig, TruthCameraRig

FLAP = CATALOGUE["pose_stale"]  # a dwell row: raise_after_s, clear_after_s


# ---------------------------------------------------------------- the board (pure)
def test_a_condition_toggling_every_100_ms_is_one_episode():
    b = AlarmBoard()
    reports = 0
    t = 0.0
    while t < 30.0:  # set for 100 ms, absent for 100 ms, for 30 s
        reports += b.set("pose_stale", "stale", t)
        b.clear("pose_stale", t + 0.1)
        t += 0.2
    assert b.episodes("pose_stale") == 1 and reports == 1
    assert [a.code for a in b.active(t)] == ["pose_stale"]  # shown while it keeps coming back
    # over once it stayed away for clear_after_s; the next one is a new episode
    assert b.active(t + FLAP.clear_after_s + 0.1) == ()
    t2 = t + FLAP.clear_after_s + 1.0
    b.set("pose_stale", "stale", t2)
    assert b.set("pose_stale", "stale", t2 + FLAP.raise_after_s)
    assert b.episodes("pose_stale") == 2


def test_a_condition_shorter_than_its_raise_dwell_is_no_episode():
    b = AlarmBoard()
    assert not b.set("pose_stale", "one late pose", 10.0)
    assert b.pending("pose_stale") and not b.is_active("pose_stale")
    assert b.active(10.1) == ()  # not shown inside the dwell
    assert not b.clear("pose_stale", 10.2)
    assert b.active(10.2 + FLAP.clear_after_s) == () and b.episodes("pose_stale") == 0
    # one that stands for the dwell is raised (shown, counted, reported) then, and only then
    assert not b.set("pose_stale", "stale", 100.0)
    assert not b.set("pose_stale", "stale", 100.0 + FLAP.raise_after_s - 0.01)
    assert b.set("pose_stale", "stale", 100.0 + FLAP.raise_after_s)
    assert [a.code for a in b.active(100.6)] == ["pose_stale"] and b.episodes("pose_stale") == 1


def test_rows_without_a_dwell_behave_as_before():
    b = AlarmBoard()
    assert CATALOGUE["camera_freeze"].raise_after_s == 0 and CATALOGUE["camera_stalled"].raise_after_s == 0
    assert b.set("camera_freeze", "frozen", 1.0)  # at once: a frozen camera waits for nothing
    assert [a.code for a in b.active(1.0)] == ["camera_freeze"]


def test_the_freshness_rows_flap_with_a_dwell_and_the_faults_do_not():
    for code in ("pose_stale", "camera_late"):
        k = CATALOGUE[code]
        assert k.raise_after_s > 0 and k.clear_after_s >= 60.0 and k.holds_arm and k.freshness, code
    for code in ("camera_freeze", "camera_stalled"):
        k = CATALOGUE[code]
        assert k.level == "alarm" and k.raise_after_s == 0 and k.holds_arm and k.freshness, code


# ---------------------------------------------------------------- the loop (simulated clock)
class IrregularCameraRig(TruthCameraRig):
    """A live camera on a busy machine: each frame is new (different content), but they come
    ``gap(i)`` s apart instead of every 33 ms; ``stop_at``: none after that time (s)."""

    def __init__(self, gaps, stop_at=np.inf):
        super().__init__("still", noise_mm=0.05)
        self._gaps, self._due, self.stop_at, self.times = gaps, None, stop_at, []

    def capture(self, t):
        if self._due is None:
            self._due = t
        if t + 1e-9 < self._due or t >= self.stop_at:
            return None
        self._due = t + next(self._gaps)
        self.times.append(t)
        return super().capture(t)


def _session(make_session, rig, **cfg):
    rob = FollowerRobotRig()
    # the simulated clock polls the camera every control tick (8 ms), so frames come when due
    s = make_session(clock="sim", camera_fps=125.0, camera_factory=lambda *a: rig,
                     robot_factory=lambda *a: rob, **cfg)
    plan_sample(s)
    assert s.start_camera().ok
    return s, rob


def _tracking(s, rob):
    for _ in range(200):  # until the first lock (simulated time)
        s.advance(0.05)
        if s.arm("1234").ok and s.start_tracking().ok:
            return
    pytest.fail("never tracked")


def test_late_frames_are_no_frozen_camera_and_one_episode(make_session):
    """Frames every 60-120 ms, all different (11-17 fps): no camera_freeze, no camera_stalled;
    the arm still holds whenever no new frame came for 0.1 s, and what the operator sees is at
    most one camera_late episode (not one per late frame)."""
    rng = np.random.default_rng(3)
    rig = IrregularCameraRig(iter(lambda: float(rng.uniform(0.060, 0.120)), None))
    s, rob = _session(make_session, rig)
    _tracking(s, rob)
    ticks = []
    s.add_tick_listener(lambda t: ticks.append((t, rob.state, rig.times[-1])))
    s.advance(30.0)
    codes = [e.code for e in s.audit_entries()]
    assert "camera_freeze" not in codes and "camera_stalled" not in codes
    board = s._alarms.board
    assert board.episodes("camera_freeze") == 0 and board.episodes("camera_stalled") == 0
    assert board.episodes("camera_late") <= 1 and codes.count("camera_late") <= 1
    assert board.episodes("pose_stale") <= 1
    # safety unchanged: the arm never followed while the newest frame was over 0.1 s old (+ a tick)
    gaps = [t - last for t, st, last in ticks if st == "tracking"]
    assert gaps and max(gaps) <= 0.1 + 1 / 125 + 1e-9
    late = [t for t, st, last in ticks if t - last > 0.1 + 1 / 125 + 1e-9]
    assert late and all(st == "holding" for t, st, last in ticks if t - last > 0.1 + 1 / 125 + 1e-9)
    # (how much it tracks between is the resume dwell's business: engine/config.py resume_dwell_s)


def test_a_camera_that_stops_delivering_is_a_stall_not_a_freeze(make_session):
    """No frame at all: the arm holds 0.1 s after the last frame (as before), and the alarm is
    camera_stalled once no frame came for stall_after_s; the short late spell before it is none."""
    from itertools import repeat

    rig = IrregularCameraRig(repeat(1 / 30))
    s, rob = _session(make_session, rig)
    _tracking(s, rob)
    s.advance(1.0)
    rig.stop_at = s.clock()
    held = []
    s.add_tick_listener(lambda t: held.append(t) if rob.state == "holding" and not held else None)
    s.advance(1.0)
    last = rig.times[-1]
    assert held and held[0] - last <= 0.1 + 1 / 125 + 1e-9
    alerts = [e for e in s.audit_entries() if e.code in ("camera_stalled", "camera_late", "camera_freeze")]
    assert [e.code for e in alerts] == ["camera_stalled"] and alerts[0].level == "alarm"
    cfg = s.config
    assert alerts[0].t_session - last == pytest.approx(cfg.stall_after_s, abs=2 / 125)
    assert "camera_stalled" in [a.code for a in s.snapshot().alarms]


def test_a_frozen_camera_is_still_caught_at_the_first_repeat(make_session):
    """Identical frames, newly stamped: camera_freeze at once (no dwell), as before."""
    from itertools import repeat

    rig = IrregularCameraRig(repeat(1 / 30))
    s, rob = _session(make_session, rig)
    _tracking(s, rob)
    s.advance(1.0)
    t_fault = s.clock()
    assert s.inject_fault("camera-freeze").ok
    s.advance(0.3)
    frz = [e for e in s.audit_entries() if e.code == "camera_freeze"]
    assert frz and frz[0].level == "alarm" and frz[0].t_session - t_fault <= 1 / 30 + 2 / 125
    assert rob.state == "holding"


def test_fake_frames_differ_unless_frozen():
    rig = TruthCameraRig()
    a, b = rig.capture(0.0), rig.capture(0.1)
    assert isinstance(a, FakeFrame) and rig.frame_digest(a) != rig.frame_digest(b)
    rig.set_fault("camera-freeze")
    c = rig.capture(0.2)
    assert c.t_capture == 0.2 and rig.frame_digest(c) == rig.frame_digest(b)
