"""Latency prediction is on by default (issue 15): shown safe here through the whole engine on the
digital twin (real registration on simulated camera points, the real Tracker on the simulated
UR10, simulated clock) under the faults that could make an extrapolating tracker move the arm
where no measurement put the head: a frozen camera, total occlusion, a wrong (jumped) pose, and
poses that arrive too old. Truth: the simulated arm's true joint state."""

import numpy as np
import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.demo.run import DemoOptions, run_demo
from monotracker.sim.trajectories import Breathing

from .conftest import plan_sample

# a head oscillating 4 mm at 0.5 Hz (12.6 mm/s peak): the arm is really moving when a fault hits
FAST = Breathing(amplitude_mm=4.0, period_s=2.0)


@pytest.fixture(scope="module")
def planned_home(tmp_path_factory):
    home = tmp_path_factory.mktemp("planned")
    s = Session(SessionConfig(home=home, clock="sim"))
    try:
        plan_sample(s)
    finally:
        s.shutdown()
    return home


def test_prediction_is_the_default():
    assert SessionConfig().predict_target is True


@pytest.mark.parametrize("fault", ["camera-freeze", "occlude-all", "bad-pose"])
def test_faults_with_the_default_prediction_stop_the_arm_where_it_was(planned_home, fault):
    """Each fault hits where the head moves fastest (the hardest case for an extrapolating
    tracker, and the arm surely moving whatever the machine's load did to the start)."""
    seen = {}

    def grab(s):
        seen["tracker"] = s._loop.robot.rig.tracker
        seen["active_before"] = []
        s.add_tick_listener(lambda t: seen["active_before"].append(seen["tracker"].predictor.active))

    r = run_demo(DemoOptions(seconds=4.0, trajectory=FAST, fault=fault, fault_at_s=2.0, fault_at_fastest_within_s=1.0,
                             home=planned_home, config_overrides={"camera": "sim-points"}), on_tracking=grab)
    tr = seen["tracker"]
    assert tr.predictor is not None and any(seen["active_before"])  # it was extrapolating
    fr = r["fault_report"]
    assert fr["engine_reported"] is not None
    assert fr["tip_speed_before_fault_mm_s"] > 3.0  # the arm was moving: stopping is a real test
    assert fr["state_after"] == "holding" and fr["plan_intact"]
    assert fr["standstill_at_s"] is not None
    # from the detection on, the stop costs < 0.5 mm (0.33 mm measured at 17 mm/s)
    assert fr["arm_travel_after_detection_mm"] < 0.5
    if fault == "camera-freeze":
        # a repeated frame is known at capture: still within 0.1 s of the fault (the goal)
        assert fr["standstill_after_fault_s"] <= 0.1 + 1e-9
    # before the detection the arm follows the head (17 mm/s here; an occluded or wrong pose
    # is known only once the frame is estimated, ~60 ms): 0.8 (freeze) and 1.35 mm measured
    assert fr["arm_travel_after_fault_mm"] < 2.0
    # holding: no velocity survives (nothing extrapolated into the resumed tracking)
    assert not tr.predictor.active and not np.any(tr.predictor.V)


def test_stale_poses_hold_and_nothing_is_extrapolated_from_them(planned_home):
    """Poses that keep coming but arrive 250 ms after capture (over the 150 ms limit): the engine
    holds, the arm stands still, and the tracker never extrapolates from a stale pose."""
    s = Session(SessionConfig(home=planned_home, clock="sim", camera="sim-points", trajectory=FAST))
    try:
        assert s.start_camera().ok
        s.advance(0.5)
        assert s.arm("1234").ok and s.start_tracking().ok
        s.advance(2.5)
        tr = s._loop.robot.rig.tracker
        assert tr.state.value == "tracking" and tr.predictor.active
        s._loop.camera.rig.transport_delay_s = 0.25
        s.advance(0.3)
        snap = s.snapshot()
        assert snap.robot.state == "holding" and snap.pose.stale and s._loop.holding_code == "pose_stale"
        arm = s._loop.robot.rig.sim_arm
        q0 = arm.true_q.copy()
        for _ in range(50):  # 0.4 s more of stale poses: still, and never a velocity estimate
            s.advance(0.008)
            assert not tr.predictor.active
        assert np.max(np.abs(arm.true_dq)) < 1e-3
        assert np.max(np.abs(arm.true_q - q0)) < 1e-4
        # reported once it stood its dwell (alarms.CATALOGUE: pose_stale.raise_after_s, 0.5 s)
        assert any(a.code == "pose_stale" for a in s.snapshot().alerts)
    finally:
        s.shutdown()
