"""ur_rtde recovery: link up, script stopped (issue 15). Against the recording fake."""

import numpy as np
import pytest

from fake_rtde import FakeUR
from monotracker.robot import kinematics as kin
from monotracker.robot.arm import ArmProgramStopped
from monotracker.robot.sim_arm import ManualClock
from monotracker.robot.tracker import Tracker
from monotracker.robot.ur_rtde_arm import URRTDEArm
from robot_rig import offset_target, to_mm


def _rig(rate_hz=125):
    ur = FakeUR(kin.Q_READY, period=1 / rate_hz)
    clock = ManualClock()
    arm = URRTDEArm("10.0.0.2", rate_hz=rate_hz, control_factory=ur.control, receive_factory=ur.receive, clock=clock)
    tr = Tracker(arm=arm, clock=clock, rate_hz=rate_hz)
    return ur, clock, arm, tr


def _run(tr, clock, T, n, feed=True, rate_hz=125):
    for _ in range(n):
        if feed:
            tr.set_target(to_mm(T), clock())
        tr.step()
        clock.advance(1 / rate_hz)


def _tracking(rate_hz=125):
    ur, clock, arm, tr = _rig(rate_hz)
    assert tr.connect().ok and tr.arm().ok
    T = offset_target()
    tr.set_target(to_mm(T), clock())
    assert tr.start_tracking().ok
    _run(tr, clock, T, 20, rate_hz=rate_hz)
    assert tr.state.value == "tracking"
    return ur, clock, arm, tr, T


@pytest.mark.parametrize("cause, expect", [("pendant", "pendant"), ("paused", "paused"),
                                           ("protective_stop", "protective stop")])
def test_script_stopped_is_its_own_state_with_the_cause(cause, expect):
    ur, clock, arm, tr, T = _tracking()
    ur.stop_script(cause)
    _run(tr, clock, T, 3)
    snap = tr.snapshot()
    assert tr.state.value == "estopped"
    assert snap.connected  # the link is up: not a connection loss
    assert snap.program_fault == cause
    assert expect in snap.program_fault_reason and "\n" not in snap.program_fault_reason
    assert expect in tr.safety.history[-1].reason


def test_watchdog_stop_after_a_stall_is_named_watchdog():
    ur, clock, arm, tr, T = _tracking()
    clock.advance(0.2)  # the loop stalled 200 ms: the robot's 20 Hz RTDE watchdog fires
    ur.stop_script("pendant")  # the controller's runtime state says only "stopped"
    _run(tr, clock, T, 1)
    snap = tr.snapshot()
    assert snap.program_fault == "watchdog"
    assert "watchdog" in snap.program_fault_reason and "limit 50 ms" in snap.program_fault_reason


def test_never_reuploads_by_itself_and_reset_recovers():
    ur, clock, arm, tr, T = _tracking()
    ur.stop_script("pendant")
    _run(tr, clock, T, 50)  # pose stream still feeding, loop running: no self-recovery
    assert ("reuploadScript",) not in ur.calls
    assert tr.state.value == "estopped" and not ur.program_running
    # operator actions other than reset do not restart it either
    assert not tr.arm().ok and not tr.start_tracking().ok
    r = tr.connect()  # link up, script stopped: says so (not the old "could not enable the watchdog")
    assert not r.ok and "script not running" in r.reason and "reset" in r.reason
    assert ("reuploadScript",) not in ur.calls
    n = len(ur.calls)
    assert tr.reset().ok
    assert ("reuploadScript",) in ur.calls[n:]
    assert ("setWatchdog", 20.0) in ur.calls[n:]  # watchdog back on after the re-upload
    assert tr.state.value == "disarmed" and ur.program_running
    _run(tr, clock, T, 2)
    assert tr.snapshot().program_fault == ""
    # and the arm can be armed and track again
    assert tr.arm().ok
    _run(tr, clock, T, 2)
    assert tr.start_tracking().ok
    _run(tr, clock, T, 200)
    assert tr.state.value == "tracking" and tr.snapshot().tip_error_mm < 1.0


def test_reset_refused_while_protective_stop_is_active():
    ur, clock, arm, tr, T = _tracking()
    ur.stop_script("protective_stop")
    _run(tr, clock, T, 2)
    r = tr.reset()
    assert not r.ok and "protective stop" in r.reason and "\n" not in r.reason
    assert ("reuploadScript",) not in ur.calls
    assert tr.state.value == "estopped"
    ur.protective_stop = False  # cleared on the pendant
    assert tr.reset().ok and ur.program_running


def test_reset_refused_when_reupload_fails():
    ur, clock, arm, tr, T = _tracking()
    ur.stop_script("pendant")
    _run(tr, clock, T, 2)
    ur.emergency_stop = True  # pressed meanwhile: the re-upload cannot start the script
    r = tr.reset()
    assert not r.ok and "emergency" in r.reason
    assert tr.state.value == "estopped"


def test_script_stopped_while_disarmed_is_reported_and_recovered():
    ur, clock, arm, tr = _rig()
    assert tr.connect().ok
    _run(tr, clock, offset_target(), 3, feed=False)
    ur.stop_script("pendant")
    _run(tr, clock, offset_target(), 2, feed=False)
    assert tr.state.value == "estopped" and tr.snapshot().program_fault == "pendant"
    assert tr.reset().ok and ur.program_running


def test_connect_with_script_stopped_says_so_not_watchdog():
    """The old trap: connect() again failed with "could not enable the RTDE watchdog"."""
    ur, clock, arm, tr, T = _tracking()
    ur.stop_script("pendant")
    _run(tr, clock, T, 2)
    with pytest.raises(ArmProgramStopped) as ei:
        arm.connect()
    assert "script not running" in str(ei.value)


def test_no_command_is_sent_as_motion_after_the_script_stopped():
    ur, clock, arm, tr, T = _tracking()
    ur.stop_script("pendant")
    n = len(ur.calls)
    _run(tr, clock, T, 20)
    moving = [c for c in ur.calls[n:] if c[0] == "speedJ" and np.any(np.asarray(c[1]) != 0)]
    assert moving == []


@pytest.mark.parametrize("rate_hz", [125, 500])
def test_control_hz_sets_rtde_frequency_and_speedj_time(rate_hz):
    ur, clock, arm, tr, T = _tracking(rate_hz)
    assert ur.freq == {"control": rate_hz, "receive": rate_hz}
    times = {c[3] for c in ur.calls if c[0] == "speedJ"}
    assert times and all(abs(t - 1 / rate_hz) < 1e-12 for t in times)


def test_engine_rig_passes_control_hz_to_the_ur_backend(monkeypatch):
    """engine/rigs/robot builds URRTDEArm with cfg.control_hz (it used to be 125 Hz always)."""
    import monotracker.robot.ur_rtde_arm as ura
    from monotracker.engine.rigs.robot import TrackerRobotRig

    ur = FakeUR(kin.Q_READY, period=1 / 500)
    orig = ura.URRTDEArm.__init__

    def init(self, host, rate_hz=125.0, **kw):
        orig(self, host, rate_hz=rate_hz, control_factory=ur.control, receive_factory=ur.receive)

    monkeypatch.setattr(ura.URRTDEArm, "__init__", init)

    class Cfg:
        robot = "ur:10.0.0.2"
        control_hz = 500.0
        controller = "APF-A-II"
        predict_target = False
        seed = 0

    class S:
        clock = staticmethod(__import__("time").monotonic)

        def record(self, *a, **k):
            pass

        def alert(self, *a, **k):
            pass

    rig = TrackerRobotRig(Cfg(), S())
    try:
        assert ur.freq == {"control": 500.0, "receive": 500.0}
        assert rig.tracker.arm_backend.period_s == pytest.approx(1 / 500)
        ur.stop_script("pendant")
        rig.step(rig.clock())
        st = rig.status()
        assert st.state == "estopped" and st.program_fault == "pendant" and "pendant" in st.message
    finally:
        rig.close()


def test_real_time_thread_paces_with_init_and_wait_period():
    ur, clock, arm, tr = _rig()
    import time

    arm.clock = time.monotonic
    tr.clock = time.monotonic
    assert tr.connect().ok
    tr.start()
    try:
        deadline = time.monotonic() + 30
        while ur.names().count("waitPeriod") < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        tr.stop()
    names = ur.names()
    assert names.count("waitPeriod") >= 3
    i = names.index("waitPeriod")
    assert "initPeriod" in names[:i]
