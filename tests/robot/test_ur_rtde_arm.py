import numpy as np

from fake_rtde import FakeUR
from monotracker.robot import kinematics as kin
from monotracker.robot.sim_arm import ManualClock
from monotracker.robot.tracker import Tracker
from monotracker.robot.ur_rtde_arm import URRTDEArm
from robot_rig import offset_target, to_mm


def _rig(answer=True):
    ur = FakeUR(kin.Q_READY, answer=answer)
    clock = ManualClock()
    arm = URRTDEArm("10.0.0.2", rate_hz=125, control_factory=ur.control, receive_factory=ur.receive, clock=clock)
    tr = Tracker(arm=arm, clock=clock)
    return ur, clock, arm, tr


def _run(tr, clock, T, n, feed=True):
    for _ in range(n):
        if feed:
            tr.set_target(to_mm(T), clock())
        tr.step()
        clock.advance(1 / 125)


def test_no_robot_gives_one_line_error():
    ur, clock, arm, tr = _rig(answer=False)
    r = tr.connect()
    assert not r.ok and "did not answer" in r.reason and "\n" not in r.reason
    assert not tr.arm().ok


def test_streams_speedj_with_watchdog_and_stops():
    ur, clock, arm, tr = _rig()
    assert tr.connect().ok
    assert ur.calls[0] == ("setWatchdog", 20.0)
    T = offset_target()
    tr.arm()
    tr.set_target(to_mm(T), clock())
    assert tr.start_tracking().ok
    _run(tr, clock, T, 250)
    names = ur.names()
    n_speed = names.count("speedJ")
    assert n_speed >= 240  # one per cycle
    # every speedJ is followed by a watchdog kick; period passed as the time argument
    for i, c in enumerate(ur.calls):
        if c[0] == "speedJ":
            assert ur.calls[i + 1][0] == "kickWatchdog"
            assert abs(c[3] - 1 / 125) < 1e-12 and np.all(np.isfinite(c[1]))
    assert tr.snapshot().tip_error_mm < 1.0  # the fake integrates commands: we reached it
    tr.stop_tracking()
    _run(tr, clock, T, 2)
    assert "speedStop" in ur.names()[-4:]
    assert np.allclose(ur.dq, 0)


def test_stale_target_stops_with_speedstop():
    ur, clock, arm, tr = _rig()
    tr.connect(); tr.arm()
    T = offset_target()
    tr.set_target(to_mm(T), clock()); tr.start_tracking()
    _run(tr, clock, T, 20)
    _run(tr, clock, T, 30, feed=False)
    assert tr.state.value == "holding"
    i = ur.names().index("speedStop")
    assert "speedJ" not in ur.names()[i:]


def test_connection_drop_estops_and_reconnect_needs_reset():
    ur, clock, arm, tr = _rig()
    tr.connect(); tr.arm()
    T = offset_target()
    tr.set_target(to_mm(T), clock()); tr.start_tracking()
    _run(tr, clock, T, 20)
    ur.drop()
    _run(tr, clock, T, 3)
    assert tr.state.value == "estopped"
    assert not tr.snapshot().connected
    assert tr.connect().ok  # reconnect() on the existing interfaces
    assert ("reconnect",) in ur.calls
    assert not tr.start_tracking().ok  # still latched
    assert tr.reset().ok and tr.arm().ok


def test_protective_stop_is_an_arm_error():
    ur, clock, arm, tr = _rig()
    tr.connect(); tr.arm()
    ur.protective_stop = True
    _run(tr, clock, offset_target(), 2)
    assert tr.state.value == "estopped"
    assert "protective" in tr.safety.history[-1].reason


def test_real_ur_rtde_without_robot_raises_one_line_arm_error():
    """The genuine ur_rtde classes, no robot at 127.0.0.1: a clean ArmError, no traceback."""
    import pytest

    from monotracker.robot.arm import ArmError

    arm = URRTDEArm("127.0.0.1")
    with pytest.raises(ArmError) as ei:
        arm.connect()
    assert "did not answer" in str(ei.value) and "\n" not in str(ei.value)
    assert not arm.is_connected()
    arm.stop(4.0)  # stop never raises, even unconnected
