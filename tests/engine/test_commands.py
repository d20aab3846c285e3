"""Operator commands validate their input and every decision lands in the audit log."""

import numpy as np

from monotracker.sim.phantom import default_phantom

from .conftest import plan_sample


def test_fiducial_workflow_and_plan_metrics(make_session):
    s = make_session(clock="sim")
    ph = default_phantom()
    assert not s.set_entry(ph.sample_entry_lps).ok  # needs locked fiducials
    for c in ph.fiducial_centres_lps[:3]:
        assert s.add_fiducial(c).ok
    r = s.confirm_fiducials()
    assert not r.ok and "at least 4" in r.message
    assert not s.add_fiducial(ph.fiducial_centres_lps[0] + 1.0).ok  # duplicate
    assert not s.add_fiducial([1, 2]).ok
    for c in ph.fiducial_centres_lps[3:]:
        s.add_fiducial(c)
    assert s.set_fiducial_status(8, "rejected").ok
    assert s.confirm_fiducials().ok
    assert not s.set_fiducial_status(0, "rejected").ok  # locked
    assert s.use_sample_plan().ok
    snap = s.snapshot()
    assert snap.step == "register"
    exp_len = np.linalg.norm(ph.sample_target_lps - ph.sample_entry_lps)
    assert abs(snap.plan.path_length_mm - exp_len) < 1e-9
    # distance from the path segment to the nearest usable fiducial, brute force
    seg = ph.sample_entry_lps + np.linspace(0, 1, 20001)[:, None] * (ph.sample_target_lps - ph.sample_entry_lps)
    d = min(np.linalg.norm(seg - c, axis=1).min() for c in ph.fiducial_centres_lps[:8])
    assert abs(snap.plan.distance_to_fiducials_mm - d) < 1e-3
    codes = [e.code for e in s.audit_entries()]
    assert codes.count("fiducial_added") == 9 and "fiducial_rejected" in codes and "target_set" in codes


def test_snapshot_is_an_immutable_copy(make_session):
    s = make_session(clock="sim")
    plan_sample(s)
    snap = s.snapshot()
    try:
        snap.fiducials[0].centre_lps_mm[0] = 0.0
        raise AssertionError("snapshot arrays must be read-only")
    except ValueError:
        pass
    s.unlock_fiducials()
    s.set_fiducial_status(0, "rejected")
    assert snap.fiducials[0].status == "added" and s.snapshot().fiducials[0].status == "rejected"


def test_arm_needs_the_pin_and_refusals_are_audited(make_session):
    from .doubles import FollowerRobotRig, TruthCameraRig

    def camera(*a):
        rig = TruthCameraRig()
        rig.default_T_base_cam = None  # no hand-eye from the camera: the operator must set it
        return rig

    s = make_session(clock="sim", robot_factory=lambda cfg, sess: FollowerRobotRig(), camera_factory=camera)
    plan_sample(s)
    assert not s.arm("0000").ok
    r = s.arm("1234")  # the right PIN, but no pose registered for this plan yet
    assert not r.ok and "no trusted, fresh pose for this plan" in r.message
    assert s.start_camera().ok
    s.advance(0.5)
    assert s.arm("1234").ok and s.snapshot().robot.state == "armed"
    r = s.start_tracking()
    assert not r.ok and "hand-eye" in r.message
    assert not s.set_hand_eye(np.diag([1.0, 1.0, -1.0, 1.0])).ok  # a reflection is not rigid
    r = s.set_hand_eye(np.eye(4))  # arming is for one plan (issue 36): not while armed
    assert not r.ok and "disarm the robot before changing the path" in r.message
    assert s.disarm().ok and s.set_hand_eye(np.eye(4)).ok
    s.advance(0.5)
    assert s.arm("1234").ok
    assert s.stop_camera().ok  # the pose is cleared with the camera
    r = s.start_tracking()
    assert not r.ok and "pose" in r.message
    codes = [e.code for e in s.audit_entries()]
    assert "arm_refused" in codes and "arm" in codes and "start_tracking_refused" in codes


def test_subscribers_get_events_and_a_broken_one_does_no_harm(make_session):
    s = make_session(clock="sim")
    got = []
    s.subscribe(lambda e: 1 / 0)
    unsub = s.subscribe(got.append)
    s.add_fiducial([0, 0, 0])
    unsub()
    s.add_fiducial([50, 0, 0])
    assert [e.code for e in got] == ["fiducial_added", "fiducial_unverified"]  # no CT: manual, unverified


def test_slicer_export(make_session, tmp_path):
    import json

    s = make_session(clock="sim")
    plan_sample(s)
    files = s.export_slicer_markups(tmp_path / "out")
    assert [f.name for f in files] == ["fiducials.mrk.json", "path.mrk.json"]
    d = json.loads(files[0].read_text())
    pts = np.array([p["position"] for p in d["markups"][0]["controlPoints"]])
    assert d["markups"][0]["coordinateSystem"] == "LPS"
    assert np.allclose(pts, default_phantom().fiducial_centres_lps)


def test_volume_accessor_gives_the_loaded_ct_for_display(tmp_path):
    """The web app's slice views read the CT through Session.volume(), never a private field."""
    from monotracker.engine import Session, SessionConfig
    from monotracker.paths import sample_ct_path

    s = Session(SessionConfig(home=tmp_path, clock="sim"))
    try:
        assert s.volume() is None
        assert s.load_ct(str(sample_ct_path())).ok
        s.wait_for_job(60)
        vol = s.volume()
        assert vol is not None and vol.array.shape == (150, 269, 207)
    finally:
        s.shutdown()
