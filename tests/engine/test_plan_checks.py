"""The commands refuse nonsense plans against the CT (issue 14 item 1, issue 17 item 1).

Truth: the analytic head phantom that the sample CT was made from (skin ellipsoid, fiducial
centres, the sample entry/target), and hand-made values (a rotation scaled by 1.05, a reflection).
"""

import numpy as np
import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.engine.plan import checks as pc
from monotracker.sim.or_layout import default_layout
from monotracker.sim.phantom import default_phantom


@pytest.fixture(scope="module")
def ct_session(tmp_path_factory):
    """A session with the sample CT loaded and its detected fiducials confirmed and locked."""
    s = Session(SessionConfig(home=tmp_path_factory.mktemp("ct"), clock="sim"))
    assert s.load_sample_ct().ok
    job = s.wait_for_job(180)
    assert job.error is None, job.error
    for f in s.snapshot().fiducials:
        s.set_fiducial_status(f.id, "confirmed")
    assert s.confirm_fiducials().ok
    yield s
    s.shutdown()


def test_sample_plan_passes_every_check(ct_session):
    s = ct_session
    assert s.use_sample_plan().ok
    assert pc.plan_problems(s.plan_copy(), 4, s._ct.loaded.anatomy) == []
    assert s.plan_not_ready() is None


def test_entry_inside_the_brain_is_refused(ct_session):
    s, ph = ct_session, default_phantom()
    r = s.set_entry(ph.centre_lps)  # the middle of the head
    assert not r.ok and "skin" in r.message and "inside the head" in r.message
    r = s.set_entry([0.0, 0.0, 0.0])
    assert not r.ok and "skin" in r.message


def test_target_outside_the_head_is_refused(ct_session):
    s, ph = ct_session, default_phantom()
    out = ph.centre_lps + np.array([300.0, 0.0, 0.0])  # 300 mm out: outside head and volume
    r = s.set_target(out)
    assert not r.ok and "outside the CT volume" in r.message
    # just outside the skin but inside the volume: air
    u = np.array([1.0, 0.0, 0.0])
    p, n = ph.skin_point(u)
    r = s.set_target(np.asarray(p) + 8.0 * np.asarray(n))
    assert not r.ok and "not inside the head" in r.message


def test_path_through_a_fiducial_and_a_grazing_angle_are_refused(ct_session):
    s = ct_session
    assert s.use_sample_plan().ok
    plan = s.plan_copy()
    c = plan.fiducial_centres()[0]
    ph = default_phantom()
    # a path from a point on the skin beside fiducial 0 straight through the fiducial's ball
    why = pc.check_path(c + (c - ph.centre_lps) / np.linalg.norm(c - ph.centre_lps) * 1.0, ph.centre_lps,
                        plan.fiducials, s._ct.loaded.anatomy)
    assert why is not None and "fiducial" in why
    # nearly along the skin: entry on the skin, target 30 mm away tangentially, 12 mm under it
    e = plan.entry_lps_mm
    n = (e - ph.centre_lps) / np.linalg.norm(e - ph.centre_lps)
    t_dir = np.cross(n, [0.0, 0.0, 1.0])
    t_dir /= np.linalg.norm(t_dir)
    why = pc.check_path(e, e + 30.0 * t_dir - 12.0 * n, [], s._ct.loaded.anatomy)  # ~68 deg, still inside the head
    assert why is not None and "normal" in why


def test_added_fiducial_is_checked_in_the_ct(ct_session):
    s, ph = ct_session, default_phantom()
    assert s.unlock_fiducials().ok
    try:
        r = s.add_fiducial([0.0, 0.0, 0.0])  # the UI's old default: inside the brain
        assert not r.ok and "no dense ball" in r.message
        n0 = len(s.plan_copy().fiducials)
        r = s.add_fiducial([0.0, 0.0, 0.0], manual=True)
        assert r.ok and "unverified" in r.message
        plan = s.plan_copy()
        assert len(plan.fiducials) == n0 + 1 and plan.fiducials[-1].verified is False
        assert any(a.code == "fiducial_unverified" for a in s.snapshot().alerts)
        assert s.set_fiducial_status(plan.fiducials[-1].id, "rejected").ok
        # a real ball passes: reject a detected one, then add it back by hand at the phantom's centre
        f0 = plan.fiducials[0]
        assert s.set_fiducial_status(f0.id, "rejected").ok
        truth = ph.fiducial_centres_lps[np.argmin(np.linalg.norm(ph.fiducial_centres_lps - f0.centre_lps_mm, axis=1))]
        r = s.add_fiducial(truth, ph.fiducial_radius_mm)
        assert r.ok and "unverified" not in r.message, r.message
        assert s.plan_copy().fiducials[-1].verified is True
    finally:
        assert s.confirm_fiducials().ok


def test_a_fiducial_added_inside_the_skull_is_not_verified(ct_session):
    """Issue 36: a point in the middle of the skull shell (1200 HU inside, less around) passed
    the old mean-contrast check as a "verified ball"; it is refused, and only a manual add
    (marked unverified) takes it."""
    s, ph = ct_session, default_phantom()
    assert s.unlock_fiducials().ok
    try:
        c = ph.fiducial_centres_lps[4]
        p, _ = ph.skin_point(c - ph.centre_lps, inset_mm=8.5)  # 5 mm scalp + half the 7 mm skull
        n0 = len(s.plan_copy().fiducials)
        r = s.add_fiducial(p, ph.fiducial_radius_mm)
        assert not r.ok and "bone" in r.message, r.message
        assert len(s.plan_copy().fiducials) == n0
    finally:
        assert s.confirm_fiducials().ok


@pytest.mark.parametrize("T,word", [
    (lambda T: T @ np.diag([1.05, 1.05, 1.05, 1.0]), "rigid"),
    (lambda T: T @ np.diag([-1.0, 1.0, 1.0, 1.0]), "reflection"),
    (lambda T: T + np.diag([0, 0, 0, np.nan]), "non-finite"),
    (lambda T: np.eye(4) + np.array([[0, 0, 0, 5000.0], [0] * 4, [0] * 4, [0] * 4]), "from the robot base"),
])
def test_hand_eye_checks(T, word):
    why = pc.check_hand_eye(T(default_layout().T_base_cam))
    assert why is not None and word in why
    assert pc.check_hand_eye(default_layout().T_base_cam) is None


@pytest.mark.parametrize("K,dist,size,word", [
    ([[0, 0, 320], [0, 800, 240], [0, 0, 1]], None, (640, 480), "focal"),
    ([[800, 0, 900], [0, 800, 240], [0, 0, 1]], None, (640, 480), "principal point"),
    ([[800, 0, 320], [0, 800, 240], [0, 0, 1]], [0, np.nan, 0, 0, 0], (640, 480), "NaN"),
    ([[800, 0, 320], [0, 800, 240], [0, 0, 1]], None, (0, 480), "positive"),
    ("abc", None, (640, 480), "numbers"),
    ([[800, 0, 320], [0, 800, 240], [0, 0, 1]], None, None, "together"),
])
def test_camera_checks(K, dist, size, word):
    why = pc.check_camera(K, dist, size)
    assert why is not None and word in why


def test_no_arming_without_a_complete_valid_plan(tmp_path):
    s = Session(SessionConfig(home=tmp_path / "h", clock="sim"))
    try:
        r = s.arm("1234")
        assert not r.ok and "not ready" in r.message
        assert s.snapshot().robot.state == "disarmed"
    finally:
        s.shutdown()


def test_a_camera_started_on_another_fiducial_set_cannot_arm(tmp_path):
    from .conftest import plan_sample
    from .doubles import FollowerRobotRig, TruthCameraRig

    cam, rob = TruthCameraRig("still"), FollowerRobotRig()
    s = Session(SessionConfig(home=tmp_path / "h", clock="sim"), camera_factory=lambda *a: cam,
                robot_factory=lambda *a: rob)
    try:
        plan_sample(s)
        assert s.start_camera().ok
        s.advance(0.3)
        assert s.unlock_fiducials().ok
        f = s.plan_copy().usable_fiducials()[0]
        # unlocking stops the camera and forgets the pose: it was registered against the old set
        assert not s.snapshot().camera.running and s.snapshot().pose is None
        assert s.set_fiducial_status(f.id, "rejected").ok
        assert s.confirm_fiducials().ok
        r = s.arm("1234")
        assert not r.ok and "no trusted, fresh pose for this plan" in r.message
        # a camera started before the change would register against the old set: refused too
        s._loop.camera.rig_fiducials = np.zeros((3, 3))  # what a rig started on another set remembers
        assert s.start_camera().ok
        s._loop.camera.rig_fiducials = np.zeros((3, 3))
        s.advance(0.3)
        r = s.arm("1234")
        assert not r.ok and "fiducial set changed" in r.message
        assert s.stop_camera().ok and s.start_camera().ok
        s.advance(0.3)
        assert s.arm("1234").ok
    finally:
        s.shutdown()
