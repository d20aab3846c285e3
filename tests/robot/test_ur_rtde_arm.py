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


def test_failed_command_still_ends_with_speedstop():
    """speedJ reached the robot but the watchdog kick after it failed: the e-stop that follows
    must send speedStop (the robot may be moving at the last speed), not skip it."""
    ur, clock, arm, tr = _rig()
    tr.connect(); tr.arm()
    T = offset_target()
    tr.set_target(to_mm(T), clock()); assert tr.start_tracking().ok
    _run(tr, clock, T, 5)
    # stop the stream once: the robot keeps its last speed until told otherwise
    ur.fail_kick = True
    _run(tr, clock, T, 1)
    assert tr.state.value == "estopped"
    i = max(k for k, c in enumerate(ur.calls) if c[0] == "speedJ" and np.any(c[1]))
    assert np.allclose(ur.dq, 0)  # speed 0 commanded at once (the robot ramps down)
    _run(tr, clock, T, 3)
    assert "speedStop" in ur.names()[i:]  # and the speed mode ended once at rest
    assert not any(c[0] == "speedJ" and np.any(c[1]) for c in ur.calls[i + 1:])


def test_first_speedj_failing_still_ends_with_speedstop():
    """The very first speedJ of a session raises after being sent (e.g. the socket died
    mid-call): the e-stop must still send speedStop."""
    ur, clock, arm, tr = _rig()
    tr.connect(); tr.arm()
    T = offset_target()
    tr.set_target(to_mm(T), clock()); assert tr.start_tracking().ok
    ur.fail_kick = True
    _run(tr, clock, T, 1)
    assert tr.state.value == "estopped"
    assert np.allclose(ur.dq, 0)
    _run(tr, clock, T, 3)
    assert "speedStop" in ur.names()


def test_non_finite_or_short_joint_state_from_the_robot_estops():
    for field, value in (("q", np.nan), ("dq", np.inf), ("q", None)):
        ur, clock, arm, tr = _rig()
        tr.connect(); tr.arm()
        T = offset_target()
        tr.set_target(to_mm(T), clock()); assert tr.start_tracking().ok
        _run(tr, clock, T, 5)
        n_speed = sum(1 for c in ur.calls if c[0] == "speedJ" and np.any(c[1]))
        if value is None:
            ur.q = ur.q[:5]
        elif field == "q":
            ur.q[2] = value
        else:
            ur.dq[1] = value
        _run(tr, clock, T, 3)
        assert tr.state.value == "estopped", (field, value)
        assert sum(1 for c in ur.calls if c[0] == "speedJ" and np.any(c[1])) == n_speed
        assert "speedStop" in ur.names()[-8:] and np.allclose(ur.dq, 0)


def test_random_operator_and_stream_faults_never_command_motion_outside_tracking():
    """Fuzz: random operator actions, link drops/reconnects and pose-stream faults. Every
    non-zero speedJ that reaches the robot is sent while the safety state is 'tracking', and after an
    e-stop none is sent until reset, arm and start_tracking were all done by the operator."""
    rng = np.random.default_rng(7)
    ur, clock, arm, tr = _rig()
    states_at_speedj = []
    real_control = ur.control

    def control(host, freq):
        c = real_control(host, freq)
        orig = c.speedJ

        def speedJ(qd, acceleration=0.5, time=0.0):
            if np.any(qd):  # speed 0 is how a stop decelerates: not motion
                states_at_speedj.append((tr.safety.state.value, ops_since_estop[0]))
            return orig(qd, acceleration, time)

        c.speedJ = speedJ
        return c

    ur_control_patch = control
    arm._control_factory = ur_control_patch
    ops_since_estop = [set(["reset", "arm", "start"])]
    tr.connect()
    T0 = offset_target((0.02, 0.0, 0.0), 0.0)
    for i in range(1500):
        r = rng.random()
        T = T0.copy()
        T[:3, 3] += 0.002 * np.sin(0.01 * i)
        stamp = clock()
        if r < 0.02:
            tr.estop("fuzz"); ops_since_estop[0] = set()
        elif r < 0.05:
            if tr.reset().ok:
                ops_since_estop[0].add("reset")
        elif r < 0.09:
            if tr.arm().ok:
                ops_since_estop[0].add("arm")
        elif r < 0.14:
            if tr.start_tracking().ok:
                ops_since_estop[0].add("start")
        elif r < 0.15:
            tr.stop_tracking()
        elif r < 0.16:
            tr.disarm()
        elif r < 0.17:
            ur.drop()
        elif r < 0.19:
            tr.connect()
        elif r < 0.22:
            T[0, 3] = np.nan
        elif r < 0.25:
            T[:3, 3] += 0.05  # jump
        elif r < 0.27:
            stamp = clock() + 1.0  # clock fault
        elif r < 0.35:
            T = None  # camera silent
        if T is not None:
            tr.set_target(to_mm(T), stamp)
        tr.step()
        clock.advance(1 / 125)
    assert len(states_at_speedj) > 50  # it did track for a good part of the run
    assert {s for s, _ in states_at_speedj} == {"tracking"}
    assert all(ops >= {"reset", "arm", "start"} for _, ops in states_at_speedj)


def test_hold_on_a_moving_ur_does_not_block_or_starve_the_watchdog():
    """A stale hold while the arm moves: the stop must not be a blocking speedStop from speed
    (ur_rtde waits for stopj to finish, no watchdog update meanwhile: the 20 Hz watchdog would
    stop the program and every later command would fail). The arm decelerates within the
    acceleration limit, speedStop still ends the speed mode once it is at rest, and tracking
    resumes by itself when poses return."""
    ur, clock, arm, tr = _rig()
    tr.connect(); tr.arm()
    T = offset_target((0.08, 0.0, 0.0), 0.0)
    tr.set_target(to_mm(T), clock()); assert tr.start_tracking().ok
    _run(tr, clock, T, 40)
    assert np.abs(ur.dq).max() > 0.1  # moving fast
    _run(tr, clock, T, 40, feed=False)  # camera silent: hold
    assert tr.state.value == "holding"
    assert ur.program_running, "a blocking speedStop starved the RTDE watchdog"
    assert max(ur.blocked_s) <= 1.0 / ur.watchdog_hz
    assert np.allclose(ur.dq, 0)
    names = ur.names()
    assert "speedStop" in names
    # the deceleration went out as speed 0 at the hold deceleration (the robot ramps at a)
    i_hold = max(i for i, c in enumerate(ur.calls) if c[0] == "speedJ" and np.any(c[1]))
    zero = [c for c in ur.calls[i_hold + 1:] if c[0] == "speedJ"]
    assert zero and all(not np.any(c[1]) and c[2] == tr.safety.cfg.joint_accel for c in zero)
    cmds = [c for c in ur.calls if c[0] == "speedJ"]
    _run(tr, clock, T, 20)
    assert tr.state.value == "tracking"
    assert ur.names().count("speedJ") > len(cmds)
