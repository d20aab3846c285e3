"""A frozen camera as a real one freezes: frames keep coming, newly stamped, bit for bit the same
content (issue 15). Detected at the first repeat; the arm stands still within 0.1 s of the fault."""

import time

import numpy as np
import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.demo.run import DemoOptions, run_demo
from monotracker.engine.plan import load_plan
from monotracker.engine.rigs.sim import ProjectedFiducialRig
from monotracker.sim.phantom import default_phantom
from monotracker.sim.trajectories import Breathing


def _planned_home(tmp_path):
    home = tmp_path / "home"
    s = Session(SessionConfig(home=home, clock="sim"))
    try:
        ph = default_phantom()
        for c in ph.fiducial_centres_lps:
            assert s.add_fiducial(c, ph.fiducial_radius_mm).ok
        assert s.confirm_fiducials().ok and s.use_sample_plan().ok
    finally:
        s.shutdown()
    return home


def test_sim_freeze_repeats_the_frame_bit_for_bit_with_new_stamps(tmp_path):
    rig = ProjectedFiducialRig(load_plan(_planned_home(tmp_path) / "plan.json"), trajectory="still")
    a, b = rig.capture(1.0), rig.capture(1.0 + 1 / 30)
    assert rig.frame_digest(a) != rig.frame_digest(b)  # sensor noise: never the same twice
    rig.set_fault("camera-freeze")
    c, d = rig.capture(1.0 + 2 / 30), rig.capture(1.0 + 3 / 30)
    assert c.t_capture == 1.0 + 2 / 30 and d.t_capture == 1.0 + 3 / 30  # the driver stamps on
    assert np.array_equal(c.points_px, b.points_px) and np.array_equal(d.points_px, b.points_px)
    assert rig.frame_digest(c) == rig.frame_digest(b) == rig.frame_digest(d)


def test_real_clock_rig_never_estimates_a_repeated_frame(tmp_path):
    rig = ProjectedFiducialRig(load_plan(_planned_home(tmp_path) / "plan.json"), trajectory="still")
    rig.start()
    try:
        deadline = time.monotonic() + 60
        while rig.latest_sample() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert rig.latest_sample() is not None
        rig.set_fault("camera-freeze")
        time.sleep(0.05)
        rig.poll_frame_info()
        info = []
        while len(info) < 3 and time.monotonic() < deadline:
            info += rig.poll_frame_info()
            time.sleep(0.02)
        assert len(info) >= 3 and len({d for _, d in info}) == 1  # repeats, newly stamped
        assert len({t for t, _ in info}) == len(info)
        # no pose from a repeated frame: nothing newer than the first of the identical frames
        # (the original may be among them; a frame captured before the freeze may still finish
        # estimating meanwhile on a loaded machine, so no snapshot of "the latest" is taken)
        assert rig.latest_sample().t_capture <= min(t for t, _ in info)
    finally:
        rig.stop()


def test_frozen_camera_detected_at_the_first_repeat_and_arm_still_within_0_1_s(tmp_path):
    fast = Breathing(amplitude_mm=4.0, period_s=2.0)  # 12.6 mm/s peak: the arm is moving
    # the freeze hits where the head moves fastest (the arm surely moving, whatever the load did
    # to when tracking started), and right after a frame: the slowest detection
    r = run_demo(DemoOptions(seconds=4.0, trajectory=fast, fault="camera-freeze", fault_at_s=2.0,
                             fault_at_fastest_within_s=1.0, home=_planned_home(tmp_path),
                             config_overrides={"camera": "sim-points"}))
    fr = r["fault_report"]
    assert fr["engine_reported"].startswith("[alarm] camera_freeze") and "bit for bit" in fr["engine_reported"]
    assert fr["tip_speed_before_fault_mm_s"] > 3.0
    # simulated clock (lock-step; the sim-points estimator is far faster than a frame period):
    # the first repeated frame comes at most one frame period after the fault
    assert fr["detection_delay_s"] <= 2 / 30 + 1e-9
    assert fr["standstill_after_fault_s"] <= 0.1 + 1e-9
    # the stop itself: < 0.5 mm; before the detection the arm follows the head (up to one frame
    # period at 17 mm/s: 0.5 mm without prediction, 0.8 mm with it, measured)
    assert fr["arm_travel_after_detection_mm"] < 0.5
    assert fr["arm_travel_after_fault_mm"] < 1.0
    assert fr["state_after"] == "holding" and fr["plan_intact"]
    # the physics the report states: the tip speed x (detection + the simulated arm's 8 ms delay
    # + 12 ms lag); the stop adds nothing of its own to it (measured 0.57-0.86 mm of travel
    # against 0.71-1.03 mm of physics over five freeze phases at 19.8 mm/s)
    assert fr["arm_response_s"] == pytest.approx(0.020)
    assert fr["travel_physics_mm"] == pytest.approx(fr["tip_speed_before_fault_mm_s"] * (fr["detection_delay_s"] + 0.020))
    assert fr["arm_travel_after_fault_mm"] < 1.1 * fr["travel_physics_mm"]


def test_a_pose_in_flight_at_the_freeze_detection_does_not_resume_tracking(tmp_path):
    """The rendered camera's registration takes longer than the 3 ms between a frame's 30 ms
    transport and the next frame, so the last frame before the freeze is still being estimated
    when its repeat is detected: its pose is trusted and fresh, but the camera is still frozen.
    It resumed tracking for one control cycle (with a 'resumed' alert); the arm must hold."""
    states, poses = [], []

    def watch(s):
        s.add_tick_listener(lambda t: states.append((t, s.robot_status().state)))
        s.add_pose_listener(lambda smp, trusted, now: poses.append((now, trusted, smp.t_capture)))

    r = run_demo(DemoOptions(seconds=3.0, trajectory=Breathing(amplitude_mm=4.0, period_s=2.0), fault="camera-freeze",
                             fault_at_s=1.5, home=_planned_home(tmp_path)), on_tracking=watch)
    fr = r["fault_report"]
    t_det = fr["detected_at_s"]
    assert fr["engine_reported"].startswith("[alarm] camera_freeze")
    # the premise: a trusted pose of a frame captured before the freeze arrived after its detection
    assert [p for p in poses if p[1] and p[0] >= t_det - 1e-9 and p[2] < fr["injected_at_s"]], \
        "no pose was in flight at the detection: this test no longer exercises the case"
    assert not [a for a in r["alerts"] if a["code"] == "resumed" and a["t"] >= t_det - 1e-3]
    after = [st for t, st in states if t >= t_det - 1e-9]
    assert after and set(after) == {"holding"}
