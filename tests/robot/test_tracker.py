import numpy as np
import pytest

from robot_rig import Rig, offset_target, ready_tip_pose, to_mm


@pytest.mark.parametrize("variant", ["APF-A-I", "APF-A-II"])
def test_admittance_variants_converge_to_target(variant):
    rig = Rig(variant)
    T = offset_target()
    rig.start(T)
    snaps = rig.run(3.0, T)
    s = snaps[-1]
    assert s.state == "tracking"
    assert s.tip_error_mm < 0.05 and s.angle_error_deg < 0.05
    # truth from the simulated arm, not the tracker's own estimate
    from monotracker.robot import kinematics as kin
    tip = kin.fk(rig.arm.true_q) @ kin.NeedleTool().T_tool0_tip
    assert np.linalg.norm(tip[:3, 3] - T[:3, 3]) < 1e-4


def test_apf_v_moves_towards_target():
    rig = Rig("APF-V")
    T = offset_target()
    rig.start(T)
    snaps = rig.run(3.0, T)
    assert snaps[-1].tip_error_mm < 0.25 * snaps[0].tip_error_mm


def test_apf_a_ii_switches_to_near_stage():
    rig = Rig("APF-A-II")
    T = offset_target()
    rig.start(T)
    stages = [s.stage for s in rig.run(2.0, T)]
    assert stages[0] == "far" and stages[-1] == "near"


def test_no_motion_unless_armed_and_tracking():
    rig = Rig()
    T = offset_target()
    rig.tracker.connect()
    rig.tracker.set_target(to_mm(T), rig.clock())
    assert not rig.tracker.start_tracking().ok  # not armed
    q0 = rig.arm.true_q.copy()
    rig.run(0.5, T)
    assert np.allclose(rig.arm.true_q, q0)
    assert rig.tracker.state.value == "disarmed"


def _moving(t):
    from monotracker.geometry import rotation_about_axis  # noqa: F401
    T = ready_tip_pose()
    T[:3, 3] += [0.01 * np.sin(1.5 * t), 0.0, 0.0]
    return T


def _track_delayed(predict):
    """Feed targets captured 60 ms earlier (stamped with their capture time) at 25 Hz."""
    rig = Rig(predict_target=predict)
    rig.start(_moving(0.0))
    errs = []
    for i in range(int(6.0 * 125)):
        t = rig.clock()
        if i % 5 == 0:
            stamp = max(t - 0.06, 0.0)
            rig.tracker.set_target(to_mm(_moving(stamp)), stamp)
        rig.tracker.step()
        rig.clock.advance(1 / 125)
        rig.arm.advance_to(rig.clock())
        if t > 2.0:
            from monotracker.robot import kinematics as kin
            tip = kin.fk(rig.arm.true_q) @ kin.NeedleTool().T_tool0_tip
            errs.append(np.linalg.norm(tip[:3, 3] - _moving(rig.clock())[:3, 3]))
    return np.sqrt(np.mean(np.square(errs))), rig


def test_latency_prediction_reduces_tracking_error():
    e_plain, _ = _track_delayed(False)
    e_pred, rig = _track_delayed(True)
    assert e_pred < 0.6 * e_plain
    # a rejected pose resets the estimate
    assert np.linalg.norm(rig.tracker.predictor.V) > 0
    bad = to_mm(ready_tip_pose())
    bad[0, 0] = np.nan
    rig.tracker.set_target(bad, rig.clock())
    assert np.linalg.norm(rig.tracker.predictor.V) == 0


def test_invalid_flag_holds_then_resumes():
    rig = Rig()
    T = offset_target()
    rig.start(T)
    rig.run(0.2, T)
    rig.run(0.2, T, valid=False)
    assert rig.tracker.state.value == "holding"
    assert "no valid pose" in rig.tracker.safety.history[-1].reason
    rig.run(0.1, T)
    assert rig.tracker.state.value == "tracking"
