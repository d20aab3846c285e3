"""The digital-twin room and head motions: geometry checked against independent computations."""

import numpy as np

from monotracker.geometry import apply_transform, invert_transform
from monotracker.sim.or_layout import default_layout
from monotracker.sim.scenes import default_K


def test_entry_and_path_placed_as_documented():
    L = default_layout()
    ph = L.phantom
    e = apply_transform(L.T_base_ct0, ph.sample_entry_lps)
    assert np.allclose(e, [550, 350, 150])
    # the patch normal (view direction) points up in the base frame
    assert np.allclose(L.T_base_ct0[:3, :3] @ ph.view_direction_lps, [0, 0, 1], atol=1e-12)
    T = L.planned_needle_pose()
    g = apply_transform(L.T_base_ct0, ph.sample_target_lps)
    assert T[2, 2] < -0.8  # the needle points down into the head
    assert np.allclose(T[:3, 3] + np.linalg.norm(g - e) * T[:3, 2], g)


def test_camera_sees_all_fiducials_from_450_mm():
    L = default_layout()
    Xc = apply_transform(L.T_cam_ct0, L.phantom.fiducial_centres_lps)
    centroid = apply_transform(L.T_cam_ct0, L.patch_centre_ct)
    assert np.allclose(centroid[:2], 0, atol=1e-9) and abs(centroid[2] - 450) < 1e-9
    K = default_K()
    uv = (Xc / Xc[:, 2:]) @ K.T
    assert np.all((uv[:, 0] > 0) & (uv[:, 0] < 1280) & (uv[:, 1] > 0) & (uv[:, 1] < 720))
    # each ball faces the camera (outward normal within 80 deg of the line of sight)
    cam_ct = apply_transform(invert_transform(L.T_cam_ct0), np.zeros(3))
    for c in L.phantom.fiducial_centres_lps:
        n = L.phantom.skin_point(c - L.phantom.centre_lps)[1]
        v = cam_ct - c
        assert n @ v / np.linalg.norm(v) > np.cos(np.radians(80))


def test_planned_pose_is_reachable_by_the_ur10():
    from monotracker.engine.rigs.robot import standby_configuration
    from monotracker.robot.targets import reachable

    L = default_layout()
    assert reachable(L.planned_needle_pose()).ok
    assert standby_configuration(L) is not None


def test_true_poses_follow_the_trajectory_in_both_frames():
    """T_base_cam @ T_cam_ct(t) == T_base_ct(t) for a moving head (one truth, two frames)."""
    L = default_layout()
    m = L.motion("breathing")
    for t in (0.0, 0.7, 1.9):
        assert np.allclose(L.T_base_cam @ L.T_cam_ct(m, t), L.T_base_ct(m, t), atol=1e-9)
    assert not np.allclose(L.T_base_ct(m, 1.0), L.T_base_ct0)
