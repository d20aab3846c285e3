"""Arming is consent to one plan, and an e-stop is latched even before a robot is connected (issue 36).

Before: entry, target or hand-eye changed while HOLDING were saved, the camera restarted on the
new plan and the arm resumed tracking onto the new path by itself; an e-stop pressed before the
robot was connected left nothing latched, so arming went ahead afterwards.
"""

import numpy as np
import pytest

from monotracker.geometry import make_transform, rotation_about_axis
from monotracker.sim.or_layout import default_layout
from monotracker.sim.phantom import default_phantom

from .conftest import plan_sample
from .doubles import FollowerRobotRig, TruthCameraRig

#: the lines the operator reads (issue 36)
ENGAGED_REFUSAL = ("disarm the robot before changing the path (arming is for one plan: arm again with the PIN "
                   "after the change)")
ESTOP_LATCHED = "the e-stop is latched; reset the e-stop first"

#: the robot rigs under test: the double, and the in-process tracker with its safety layer
#: (the control-process rig sends the same commands to the same tracker in a child process)
RIGS = {"double": lambda *a: FollowerRobotRig(), "tracker": None}


def _holding(make_session, rig, cameras=None):
    """A session tracking the sample plan, then HOLDING (all fiducials occluded)."""
    cams = [] if cameras is None else cameras

    def camera(*a):
        cam = TruthCameraRig()
        if len(cams) >= 1 and getattr(cams[0], "next_K", None) is not None:
            cam.K = cams[0].next_K
        cams.append(cam)
        return cam

    kw = {} if RIGS[rig] is None else {"robot_factory": RIGS[rig]}
    s = make_session(clock="sim", camera_factory=camera, **kw)
    plan_sample(s)
    if s.plan_copy().T_base_cam is None:
        assert s.set_hand_eye(default_layout().T_base_cam).ok
    assert s.start_camera().ok
    s.advance(0.5)
    r = s.arm("1234")
    assert r.ok, r.message
    r = s.start_tracking()
    assert r.ok, r.message
    s.advance(0.3)
    assert s.inject_fault("occlude-all").ok
    s.advance(0.3)
    assert s.snapshot().robot.state == "holding"
    return s, cams


def _codes(s):
    return [a.code for a in s.snapshot().alarms]


@pytest.mark.parametrize("rig", sorted(RIGS))
def test_path_and_hand_eye_are_refused_while_holding_and_the_arm_never_moves_onto_a_new_path(make_session, rig):
    s, _ = _holding(make_session, rig)
    ph = default_phantom()
    before = s.plan_copy()
    T_rot = default_layout().T_base_cam @ make_transform(rotation_about_axis(np.array([0.0, 0.0, 1.0]),
                                                                             np.radians(2.0)), np.zeros(3))
    for r in (s.set_entry(ph.sample_entry_lps + np.array([0.0, 2.0, 0.0])),
              s.set_target(ph.sample_target_lps + np.array([3.0, 0.0, 0.0])),
              s.set_hand_eye(T_rot)):
        assert not r.ok and r.message == ENGAGED_REFUSAL
    after = s.plan_copy()
    assert np.array_equal(after.entry_lps_mm, before.entry_lps_mm)
    assert np.array_equal(after.target_lps_mm, before.target_lps_mm)
    assert np.array_equal(after.T_base_cam, before.T_base_cam) and after.revision == before.revision
    s.advance(0.5)  # still occluded: the arm holds, on the plan it was armed for
    assert s.snapshot().robot.state == "holding"
    # the same refusal while ARMED (not tracking), then after disarming the change goes through
    assert s.stop_tracking().ok and s.snapshot().robot.state == "armed"
    assert s.set_target(ph.sample_target_lps + np.array([3.0, 0.0, 0.0])).message == ENGAGED_REFUSAL
    assert s.disarm().ok
    assert s.set_target(ph.sample_target_lps + np.array([3.0, 0.0, 0.0])).ok


@pytest.mark.parametrize("rig", sorted(RIGS))
def test_another_revision_reaching_a_holding_robot_disarms_it(make_session, rig):
    """The camera restarted with another calibration while HOLDING: the plan's camera changes,
    so the robot is disarmed (``plan_changed_armed``) and never resumes by itself."""
    s, cams = _holding(make_session, rig)
    cams[0].next_K = np.array([[1120.0, 0, 640], [0, 1120.0, 360], [0, 0, 1]])  # recalibrated camera
    assert s.stop_camera().ok
    r = s.start_camera()
    assert r.ok, r.message
    assert np.allclose(s.plan_copy().K, cams[0].next_K)  # the revision was saved ...
    snap = s.snapshot()
    assert snap.robot.state == "disarmed"  # ... after the robot was disarmed
    alarm = next(a for a in snap.alarms if a.code == "plan_changed_armed")
    assert "holding" in alarm.message and "arm again with the PIN" in alarm.message
    assert s.inject_fault("none").ok
    s.advance(1.0)  # trusted poses again: nothing resumes without the operator
    snap = s.snapshot()
    assert snap.pose.trusted and snap.robot.state == "disarmed"
    assert "plan_changed_armed" in [e.code for e in s.audit_entries()]
    r = s.arm("1234")  # consent to the new plan
    assert r.ok, r.message
    assert "plan_changed_armed" not in _codes(s)


@pytest.mark.parametrize("channel", ["estop", "request_estop"])
def test_an_estop_before_the_robot_is_connected_is_latched(make_session, channel):
    cam = TruthCameraRig()
    s = make_session(clock="sim", camera_factory=lambda *a: cam, robot_factory=lambda *a: FollowerRobotRig())
    plan_sample(s)
    assert s.set_hand_eye(default_layout().T_base_cam).ok
    assert s.start_camera().ok
    s.advance(0.5)
    getattr(s, channel)()  # no robot yet
    snap = s.snapshot()
    assert snap.robot.state == "estopped"
    if channel == "estop":
        assert "estop" in _codes(s)
    r = s.arm("1234")
    assert not r.ok and r.message == ESTOP_LATCHED
    assert s.connect_robot().ok
    s.advance(0.1)
    assert s.snapshot().robot.state == "estopped"  # the robot connected meanwhile starts e-stopped
    assert s.arm("1234").message == ESTOP_LATCHED
    assert s.reset_estop().ok
    s.advance(0.1)
    assert s.snapshot().robot.state == "disarmed" and "estop" not in _codes(s)
    r = s.arm("1234")
    assert r.ok, r.message


def test_reset_before_the_robot_is_connected_releases_the_latch(make_session):
    cam = TruthCameraRig()
    s = make_session(clock="sim", camera_factory=lambda *a: cam, robot_factory=lambda *a: FollowerRobotRig())
    plan_sample(s)
    assert s.set_hand_eye(default_layout().T_base_cam).ok
    assert s.estop().ok and s.snapshot().robot.state == "estopped"
    assert s.reset_estop().ok
    assert s.snapshot().robot.state == "disarmed" and "estop" not in _codes(s)
    assert s.start_camera().ok
    s.advance(0.5)
    r = s.arm("1234")
    assert r.ok, r.message


@pytest.mark.serial  # the engine on the real clock: the serial lane (tests/conftest.py)
def test_the_control_process_connected_after_an_early_stop_starts_e_stopped(make_session):
    """clock="real": the robot's control loop runs in its own process (``robot/control_process.py``);
    the latched stop reaches it as it connects, acknowledged by the child itself."""
    s = make_session(clock="real")
    s.request_estop()  # the stop channel, before any robot exists
    assert s.snapshot().robot.state == "estopped"
    r = s.connect_robot()
    assert r.ok, r.message
    rig = s._loop.robot.rig
    assert getattr(rig, "proc", None) is not None, "expected the control-process rig"
    assert rig.proc.state().state == "estopped"  # published by the control process
    assert s.arm("1234").message == ESTOP_LATCHED
