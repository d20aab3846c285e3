"""Safety layer and state machine, exercised through the tracker on the simulated arm."""

import numpy as np

from monotracker.robot import kinematics as kin
from robot_rig import RATE, Rig, offset_target, ready_tip_pose, to_mm


def _states(rig):
    return [(p.from_state.value, p.to_state.value) for k, p in rig.events if k == "transition"]


def test_transitions_are_logged_with_reason_and_time():
    rig = Rig()
    T = offset_target()
    rig.start(T)
    rig.run(0.2, T)
    rig.tracker.stop_tracking()
    rig.tracker.disarm()
    assert _states(rig) == [("disarmed", "armed"), ("armed", "tracking"), ("tracking", "armed"), ("armed", "disarmed")]
    for k, tr in rig.events:
        if k == "transition":
            assert tr.reason and np.isfinite(tr.t)


def test_stale_target_holds_decelerates_and_auto_resumes():
    rig = Rig()
    T = offset_target((0.08, 0.0, 0.0), 0.0)
    rig.start(T)
    rig.run(0.3, T)  # moving fast towards the target
    assert np.linalg.norm(rig.arm.true_dq) > 0.05
    v0 = np.abs(rig.arm.true_dq).max()
    dqs = []
    for _ in range(int(1.0 * RATE)):  # camera stops delivering; truth sampled every cycle
        rig.run(1.0 / RATE, T, feed=False)
        dqs.append(rig.arm.true_dq.copy())
    assert rig.tracker.state.value == "holding"
    assert "no fresh" in rig.tracker.snapshot().last_transition.reason
    assert np.linalg.norm(rig.arm.true_dq) < 1e-3  # stopped
    # braked within the joint acceleration limit (no instantaneous zero), but no slower than
    # needed: standstill within stale_s + v0 / a + the arm's delay and lag
    cfg = rig.tracker.safety.cfg
    dqs = np.array(dqs)
    assert (np.abs(np.diff(dqs, axis=0)).max(axis=1) * RATE).max() <= cfg.joint_accel * 1.001
    t_still = (np.argmax(np.abs(dqs).max(axis=1) < 1e-3) + 1) / RATE
    assert t_still <= cfg.stale_s + v0 / cfg.joint_accel + 0.08
    rig.run(0.1, T)  # fresh targets again
    assert rig.tracker.state.value == "tracking"


def test_target_jump_and_nan_hold_until_operator():
    rig = Rig()
    T = ready_tip_pose()
    rig.start(T)
    rig.run(0.2, T)
    J = T.copy()
    J[:3, 3] += [0.05, 0, 0]
    rig.run(0.3, J)
    assert rig.tracker.state.value == "holding"
    assert "jump" in rig.tracker.safety.history[-1].reason
    q_hold = rig.arm.true_q.copy()
    rig.run(0.3, J)  # still the jumped pose: stays holding, arm still
    assert rig.tracker.state.value == "holding"
    assert np.allclose(rig.arm.true_q, q_hold, atol=1e-4)
    assert rig.tracker.start_tracking().ok  # operator accepts the new pose
    rig.run(2.0, J)
    assert rig.tracker.snapshot().tip_error_mm < 0.1
    bad = to_mm(J)
    bad[0, 3] = np.nan
    assert not rig.tracker.set_target(bad, rig.clock()).ok
    assert rig.tracker.state.value == "holding"


def test_estop_is_latched_until_reset():
    rig = Rig()
    T = offset_target()
    rig.start(T)
    rig.run(0.2, T)
    rig.tracker.estop("test")
    rig.run(0.5, T)
    assert rig.tracker.state.value == "estopped"
    assert np.linalg.norm(rig.arm.true_dq) < 1e-3
    assert not rig.tracker.start_tracking().ok
    assert not rig.tracker.arm().ok
    assert rig.tracker.reset().ok
    assert rig.tracker.state.value == "disarmed"
    assert rig.tracker.arm().ok  # needs the explicit operator action again


def test_arm_disconnect_estops():
    rig = Rig()
    T = offset_target()
    rig.start(T)
    rig.run(0.2, T)
    rig.arm.drop_connection()
    rig.run(0.1, T)
    assert rig.tracker.state.value == "estopped"
    assert "connection" in rig.tracker.safety.history[-1].reason


def test_exception_in_loop_stops():
    rig = Rig()
    T = offset_target()
    rig.start(T)
    rig.run(0.2, T)

    def boom(*a, **k):
        raise RuntimeError("boom")

    rig.tracker.controller.step = boom
    rig.run(0.5, T)
    assert rig.tracker.state.value == "estopped"
    assert "boom" in rig.tracker.safety.history[-1].reason
    assert np.linalg.norm(rig.arm.true_dq) < 1e-3


def test_limits_respected_on_a_large_step():
    rig = Rig()
    T = offset_target((0.15, 0.1, -0.05), 15.0)
    rig.tracker.safety.cfg.jump_m = 1.0
    rig.tracker.safety.cfg.jump_rad = 1.0
    rig.start(T)
    snaps = rig.run(3.0, T)
    cfg = rig.tracker.safety.cfg
    cmds = np.array([s.dq_cmd for s in snaps])
    assert np.all(np.abs(cmds) <= cfg.joint_speed + 1e-9)
    acc = np.abs(np.diff(cmds, axis=0)) * RATE
    assert acc.max() <= cfg.joint_accel + 1e-6
    tips = np.array([s.T_base_tip_mm[:3, 3] for s in snaps]) / 1000.0
    speed = np.linalg.norm(np.diff(tips, axis=0), axis=1) * RATE
    assert speed.max() <= cfg.tool_speed_m_s * 1.05  # measured, includes arm lag


def test_jump_while_armed_is_just_the_new_reference():
    rig = Rig()
    rig.tracker.connect()
    rig.tracker.arm()
    T = ready_tip_pose()
    rig.tracker.set_target(to_mm(T), rig.clock())
    J = T.copy()
    J[:3, 3] += [0.05, 0, 0]
    assert rig.tracker.set_target(to_mm(J), rig.clock()).ok
    assert rig.tracker.start_tracking().ok
    assert np.allclose(rig.tracker.safety.target, J)


def _stale_hold(rig):
    T = offset_target()
    rig.start(T)
    rig.run(0.2, T)
    rig.run(0.2, T, feed=False)
    assert rig.tracker.state.value == "holding"  # stale: would resume by itself
    return T


def test_nan_pose_during_a_stale_hold_needs_the_operator():
    rig = Rig()
    T = _stale_hold(rig)
    bad = to_mm(T)
    bad[0, 3] = np.nan
    assert not rig.tracker.set_target(bad, rig.clock()).ok
    rig.run(0.2, T)  # good poses again
    assert rig.tracker.state.value == "holding"
    assert rig.tracker.start_tracking().ok


def test_jump_during_a_stale_hold_needs_the_operator():
    rig = Rig()
    T = _stale_hold(rig)
    J = T.copy()
    J[:3, 3] += [0.05, 0, 0]
    assert not rig.tracker.set_target(to_mm(J), rig.clock()).ok
    rig.clock.advance(1.0 / RATE)
    rig.run(0.2, T)  # the stream comes back to the old pose
    assert rig.tracker.state.value == "holding"


def test_arm_status_check_raising_stops_instead_of_escaping():
    """A backend whose is_connected() raises (driver bug, dead socket) must not make step()
    raise (the simulated-clock callers have no last-guard): latched e-stop and a stop."""
    rig = Rig()
    T = offset_target()
    rig.start(T)
    rig.run(0.2, T)

    def broken():
        raise OSError("socket is dead")

    rig.arm.is_connected = broken
    stops = rig.arm.stops
    snap = rig.tracker.step()
    assert rig.tracker.state.value == "estopped"
    assert "socket is dead" in rig.tracker.safety.history[-1].reason
    assert rig.arm.stops > stops
    assert snap.connected is False


def test_reconnect_before_the_loop_noticed_the_drop_does_not_resume_motion():
    """The link drops and the operator (or a retry) reconnects before the next control cycle:
    the drop must still latch an e-stop; motion never resumes by itself."""
    rig = Rig()
    T = offset_target((0.08, 0.0, 0.0), 0.0)
    rig.start(T)
    rig.run(0.2, T)
    rig.arm.drop_connection()
    r = rig.tracker.connect()
    assert r.ok
    assert rig.tracker.state.value == "estopped"
    n_cmd = rig.arm.commands
    rig.run(0.5, T)
    assert rig.arm.commands == n_cmd  # no velocity command after the drop
    assert np.linalg.norm(rig.arm.true_dq) < 1e-3


def test_connect_while_tracking_and_connected_is_a_no_op():
    rig = Rig()
    T = offset_target()
    rig.start(T)
    rig.run(0.1, T)
    assert rig.tracker.connect().ok
    assert rig.tracker.state.value == "tracking"


def test_joint_limit_braking_stops_a_lagging_arm_before_the_hard_limit():
    """Push wrist 3 / wrist 1 / elbow into their limits through the safety filter alone, on the
    simulated arm (8 ms delay, 12 ms lag): the true joint never passes the UR10's hard limit
    (URDF: +-2 pi, elbow +-pi), the command decelerates within joint_accel, and the joint
    ends up close to (not far before) the margin."""
    from monotracker.robot.safety import SafetyLayer, State
    from monotracker.robot.sim_arm import ManualClock, SimulatedArm

    hard = np.array([2 * np.pi] * 2 + [np.pi] + [2 * np.pi] * 3)
    k = kin.Kinematics()
    for j, sign in ((5, 1), (5, -1), (3, 1), (2, -1)):
        s = SafetyLayer()
        s.state, s.target, s.target_received, s.target_stamp = State.TRACKING, np.eye(4), 0.0, 0.0
        q0 = kin.Q_READY.copy()
        q0[j] = sign * (hard[j] - s.cfg.position_margin_rad - 0.3)
        clock = ManualClock()
        arm = SimulatedArm(q0=q0, clock=clock)
        arm.connect()
        cmds, qs = [], []
        for _ in range(int(2.0 * RATE)):
            q = arm.read().q
            T, J = k.fk_and_jacobian_body(q)
            want = np.zeros(6)
            want[j] = sign * 5.0
            c = s.filter_command(0.0, q, want, 1 / RATE, T, J, 1.0, None)
            arm.command_velocity(c, s.cfg.joint_accel)
            cmds.append(c[j])
            clock.advance(1 / RATE)
            arm.advance_to(clock())
            qs.append(arm.true_q[j])
        qs = np.array(qs)
        assert np.abs(qs).max() < hard[j], (j, sign)
        assert (np.abs(np.diff(cmds)) * RATE).max() <= s.cfg.joint_accel + 1e-9
        assert hard[j] - np.abs(qs[-1]) < s.cfg.position_margin_rad + 0.01  # not stopped early
        assert abs(cmds[-1]) < 1e-6
