"""A trusted pose for *this* plan: changing the plan or the camera forgets the pose."""

import numpy as np

from monotracker.sim.phantom import default_phantom

from .conftest import plan_sample
from .doubles import FollowerRobotRig, TruthCameraRig


def _registered(make_session):
    rigs = []

    def camera(*a):
        plan = a[2]
        rig = TruthCameraRig()
        rig.built_for_target = None if plan.target_lps_mm is None else plan.target_lps_mm.copy()
        rigs.append(rig)
        return rig

    s = make_session(clock="sim", camera_factory=camera, robot_factory=lambda *a: FollowerRobotRig())
    plan_sample(s)
    assert s.start_camera().ok
    s.advance(0.5)
    snap = s.snapshot()
    assert snap.pose.trusted and snap.scene.T_cam_ct is not None
    return s, rigs


def test_changing_the_path_forgets_the_pose_and_restarts_the_camera_on_the_new_plan(make_session):
    s, rigs = _registered(make_session)
    ph = default_phantom()
    new_target = ph.sample_target_lps + np.array([5.0, 0.0, 0.0])
    assert s.set_target(new_target).ok
    snap = s.snapshot()
    assert snap.pose is None and snap.scene.T_cam_ct is None  # no VALID pose at a target that is gone
    r = s.arm("1234")
    assert not r.ok and "no trusted, fresh pose for this plan" in r.message
    # the camera runs again, on a rig built with the new target
    assert snap.camera.running and len(rigs) == 2 and np.allclose(rigs[-1].built_for_target, new_target)
    s.advance(0.5)
    assert s.snapshot().pose.trusted
    assert s.arm("1234").ok
    codes = [e.code for e in s.audit_entries()]
    assert "pose_invalidated" in codes


def test_setting_the_same_point_again_keeps_the_pose(make_session):
    s, rigs = _registered(make_session)
    assert s.set_target(default_phantom().sample_target_lps).ok
    assert s.snapshot().pose.trusted and len(rigs) == 1


def test_new_plan_and_unlocked_fiducials_stop_the_camera_and_forget_the_pose(make_session):
    s, _ = _registered(make_session)
    assert s.unlock_fiducials().ok
    snap = s.snapshot()
    assert snap.pose is None and not snap.camera.running
    assert not s.arm("1234").ok
    assert s.confirm_fiducials().ok and s.start_camera().ok
    s.advance(0.5)
    assert s.snapshot().pose.trusted
    assert s.new_plan().ok
    snap = s.snapshot()
    assert snap.pose is None and not snap.camera.running and snap.scene.T_cam_ct is None


def test_stopped_or_failed_camera_clears_the_pose(make_session):
    s, _ = _registered(make_session)
    assert s.stop_camera().ok
    assert s.snapshot().pose is None
    r = s.arm("1234")
    assert not r.ok and "no pose yet" in r.message
    # a start that fails leaves no pose either
    s.shutdown()  # one session per folder (engine/session_lock.py)
    s2 = make_session(clock="sim", robot_factory=lambda *a: FollowerRobotRig())
    assert s2.new_plan().ok  # (same home folder: start from an empty plan)
    plan_sample(s2)
    assert s2.set_camera("sim-points").ok and s2.start_camera().ok
    s2.advance(1.0)
    assert s2.snapshot().pose is not None
    assert s2.stop_camera().ok and s2.set_camera("file:/nonexistent.mp4").ok
    assert not s2.start_camera().ok
    snap = s2.snapshot()
    assert snap.pose is None and [a.code for a in snap.alarms][0] == "camera_failed"


def test_path_change_while_holding_is_refused_and_after_disarming_forgets_the_pose(make_session):
    """Issue 36: the arm used to resume onto the new path by itself; arming is for one plan."""
    s, _ = _registered(make_session)
    assert s.arm("1234").ok and s.start_tracking().ok
    s.advance(0.3)
    assert s.inject_fault("occlude-all").ok
    s.advance(0.3)
    assert s.snapshot().robot.state == "holding"
    new_entry = default_phantom().sample_entry_lps + np.array([0.0, 2.0, 0.0])
    r = s.set_entry(new_entry)
    assert not r.ok and "disarm the robot before changing the path" in r.message
    assert s.snapshot().robot.state == "holding"
    assert s.disarm().ok and s.set_entry(new_entry).ok
    assert s.snapshot().pose is None and s.snapshot().robot.state == "disarmed"
    s.advance(0.5)  # the new rig has no fault: trusted poses for the new plan, the arm stays disarmed
    snap = s.snapshot()
    assert snap.pose.trusted and snap.robot.state == "disarmed"
