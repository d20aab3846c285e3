"""The simulated camera against independent geometry (OpenCV projection, analytic cones)."""

import cv2
import numpy as np

from monotracker.geometry import apply_transform, invert_transform
from monotracker.sim.camera_sim import Occluder, SceneEvents, SimulatedCamera, Stray, _finger
from monotracker.sim.trajectories import TRAJECTORIES, make_trajectory
from monotracker.sim.phantom import default_phantom


def test_camera_distance_and_view(sim_still):
    T = sim_still.T_cam_ct_at(0.0)
    ph = default_phantom()
    patch_cam = apply_transform(T, ph.fiducial_centres_lps.mean(0))
    assert np.allclose(patch_cam[:2], 0, atol=1e-6) and 450 < patch_cam[2] < 600
    # the camera looks along -view_direction (towards the head)
    cam_pos_ct = invert_transform(T)[:3, 3]
    v = cam_pos_ct - ph.fiducial_centres_lps.mean(0)
    assert np.allclose(v / np.linalg.norm(v), ph.view_direction_lps, atol=1e-9)


def test_truth_projection_matches_opencv(sim_still):
    img, tr = sim_still.render(0.0)
    assert img.shape == (720, 1280, 3) and img.dtype == np.uint8
    T = tr.T_cam_ct
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    ref, _ = cv2.projectPoints(default_phantom().fiducial_centres_lps, rvec, T[:3, 3], sim_still.K, sim_still.dist)
    assert np.allclose(tr.projected_centres_px, ref.reshape(-1, 2), atol=1e-6)
    assert tr.visible.all()


def test_rendered_sphere_is_the_true_ellipse():
    """The soft green mask's centroid and area equal the analytic sphere image (no distortion,
    no noise: the exact cone of tangent rays gives an ellipse with known centre and area)."""
    from monotracker.vision.camera_model import CameraModel

    cam = SimulatedCamera(camera=CameraModel(np.array([[1100, 0, 640.0], [0, 1100, 360.0], [0, 0, 1]]),
                                             np.zeros(5), (1280, 720)), noise_sigma=0, exposure_s=0)
    img, tr = cam.render(0.0)
    C = apply_transform(tr.T_cam_ct, default_phantom().fiducial_centres_lps)
    R = 4.0
    for k in range(len(C)):
        a, b, c = C[k]
        # analytic ellipse: centre (a c, b c)/(c^2-R^2) on the normalised plane
        centre = np.array([a * c, b * c]) / (c**2 - R**2) * 1100 + [640, 360]
        assert np.allclose(tr.ellipse_centres_px[k], centre, atol=1e-6)
        # area of the cone section on the plane z=1 (conic M = C C^T - (|C|^2 - R^2) I):
        # pi |det M| / det(-A)^(3/2) = pi R^2 sqrt(|C|^2 - R^2) / (c^2 - R^2)^(3/2)
        n2 = C[k] @ C[k]
        area_norm = np.pi * R**2 * np.sqrt(n2 - R**2) / (c**2 - R**2) ** 1.5
        area_px = area_norm * 1100**2
        # the rasteriser's anti-aliased coverage on its ROI (pixel centres at integers)
        roi = cam._sphere_roi(tr.projected_centres_px[k], tr.radius_px[k], 1280, 720)
        cov, _ = cam._render_sphere(C[k], R, roi, tr.T_cam_ct[:3, :3], tr.T_cam_ct[:3, 3])
        y0, y1, x0, x1 = roi
        assert abs(cov.sum() - area_px) / area_px < 0.01
        yy, xx = np.mgrid[y0:y1, x0:x1]
        cen = np.array([(cov * xx).sum(), (cov * yy).sum()]) / cov.sum()
        assert np.linalg.norm(cen - centre) < 0.02
        # and the composited image shows green exactly there
        x, y = np.round(centre).astype(int)
        assert img[y, x, 1] > img[y, x, 2]


def test_rendering_is_deterministic():
    a = SimulatedCamera(trajectory=make_trajectory("breathing"), seed=4, max_frames=3)
    b = SimulatedCamera(trajectory=make_trajectory("breathing"), seed=4, max_frames=3)
    fa = [f.image for f in a]
    fb = [f.image for f in b]
    assert len(fa) == 3 and all(np.array_equal(x, y) for x, y in zip(fa, fb))
    assert not np.array_equal(fa[0], fa[1])  # noise differs frame to frame


def test_trajectories_move_the_truth():
    for name in TRAJECTORIES:
        tr = make_trajectory(name)
        T0, T1 = tr.pose(0.0), tr.pose(21.0)
        assert np.allclose(T0[:3, :3] @ T0[:3, :3].T, np.eye(3), atol=1e-9)
        if name == "still":
            assert np.allclose(T1, np.eye(4))
        else:
            assert not np.allclose(T1, T0)


def test_occluder_hides_fiducial_in_truth(sim_still):
    px = sim_still.rest_projection()
    oc = Occluder(0.0, 10.0, _finger(60, 900, 0.0), px[3] + [300, 0], px[3] - [20, 0], sweep_s=0.0)
    cam = SimulatedCamera(events=SceneEvents(occluders=[oc]), seed=0)
    img, tr = cam.render(1.0)
    assert tr.visible_fraction[3] < 0.05 and not tr.visible[3]
    assert tr.visible.sum() >= 7
    # and the pixels at the ball are glove-coloured, not green
    x, y = np.round(tr.ellipse_centres_px[3]).astype(int)
    b, g, r = img[y, x].astype(int)
    assert r > g


def test_stray_listed_in_truth():
    cam = SimulatedCamera(events=SceneEvents(strays=[Stray(0, 5, (200.0, 150.0), 10.0, "round")]), seed=0)
    img, tr = cam.render(1.0)
    assert np.allclose(tr.stray_centres_px, [[200, 150]])
    assert img[150, 200, 1] > 200


def test_stray_over_a_ball_hides_it_in_truth(sim_still):
    px = sim_still.rest_projection()
    cam = SimulatedCamera(events=SceneEvents(strays=[Stray(0, 5, tuple(px[2] + [4.0, 0.0]), 12.0, "round")]), seed=0)
    img, tr = cam.render(1.0)
    assert tr.visible_fraction[2] < 0.2 and not tr.visible[2]
    assert tr.visible.sum() == 8
