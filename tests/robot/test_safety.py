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
        assert tr.reason and np.isfinite(tr.t)


def test_stale_target_holds_decelerates_and_auto_resumes():
    rig = Rig()
    T = offset_target((0.08, 0.0, 0.0), 0.0)
    rig.start(T)
    rig.run(0.3, T)  # moving fast towards the target
    assert np.linalg.norm(rig.arm.true_dq) > 0.05
    snaps = rig.run(1.0, T, feed=False)  # camera stops delivering
    assert rig.tracker.state.value == "holding"
    assert "no fresh" in snaps[-1].last_transition.reason
    assert np.linalg.norm(rig.arm.true_dq) < 1e-3  # stopped
    # deceleration never exceeded the configured limit by more than the arm lag allows
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
