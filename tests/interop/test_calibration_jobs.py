"""Guided calibration jobs (engine side of the browser's calibration steps), on rendered boards
(our own ray-plane renderer with real lens distortion) and the UR10's kinematics, against the
known truth: the intrinsics that rendered the boards, the camera pose that saw the arm."""

import numpy as np
import pytest

from monotracker.engine.calibration_jobs import HandEyeJob, IntrinsicsJob
from monotracker.errors import InputError
from monotracker.geometry import invert_transform, look_at, make_transform, rotation_angle_deg
from monotracker.vision.calibration import render_chessboard
from monotracker.vision.camera_model import CameraModel

PATTERN, SQUARE = (7, 5), 20.0


def _rot(rx, ry, rz):
    import cv2

    R, _ = cv2.Rodrigues(np.array([rx, ry, rz], float))
    return R


def _board_poses(rng, n):
    """Board poses filling the image at 250-400 mm with 15-40 deg tilts."""
    out = []
    for k in range(n):
        R = _rot(*rng.uniform(-0.6, 0.6, 2), rng.uniform(-0.4, 0.4)) if k else np.eye(3)
        c = np.array([rng.uniform(-60, 60), rng.uniform(-40, 40), rng.uniform(250, 400)])
        centre = np.array([(PATTERN[0] - 1) * SQUARE / 2, (PATTERN[1] - 1) * SQUARE / 2, 0])
        out.append(make_transform(R, c - R @ centre))
    return out


def test_intrinsics_job_recovers_the_camera_and_guides_the_operator(tmp_path):
    truth = CameraModel(np.array([[800.0, 0, 322.0], [0, 800.0, 238.0], [0, 0, 1]]),
                        np.array([-0.08, 0.03, 0.0, 0.0, 0.0]), (640, 480))
    rays = truth.pixel_rays(2)
    job = IntrinsicsJob(pattern=PATTERN, square_mm=SQUARE, min_views=8)
    # a frame without a board is refused with the reason
    r = job.add_view(np.full((480, 640, 3), 120, np.uint8))
    assert not r.accepted and "no 7x5 chessboard found" in r.reason and r.n_views == 0
    rng = np.random.default_rng(3)
    imgs = [render_chessboard(truth, T, PATTERN, SQUARE, rays=rays) for T in _board_poses(rng, 12)]
    first = job.add_view(imgs[0])
    assert first.accepted and "more needed" in first.reason and 0 < first.coverage < 1
    dup = job.add_view(imgs[0])
    assert not dup.accepted and "too close" in dup.reason
    with pytest.raises(InputError, match="at least 8"):
        job.solve()
    reports = [job.add_view(im) for im in imgs[1:]]
    assert sum(r.accepted for r in reports) >= 8
    last = job.status()
    assert last.ready and last.coverage > 0.5 and last.tilt_deg > 5
    res = job.solve()
    K = res.camera.K
    assert res.rms_px < 0.3 and max(res.per_view_rms_px.values()) < 0.5
    assert abs(K[0, 0] - 800) < 4 and abs(K[1, 1] - 800) < 4 and abs(K[0, 2] - 322) < 3 and abs(K[1, 2] - 238) < 3
    # the saved file loads back as the same camera
    p = job.save(tmp_path / "cam.json")
    back = CameraModel.load(p)
    assert np.allclose(back.K, K) and np.allclose(back.dist, res.camera.dist)


def test_hand_eye_job_recovers_the_camera_pose_from_the_arm():
    from monotracker.robot import kinematics as kin

    cam = CameraModel(np.array([[1100.0, 0, 640.0], [0, 1100.0, 360.0], [0, 0, 1]]),
                      np.array([-0.05, 0.01, 0.0, 0.0, 0.0]), (1280, 720))
    rays = cam.pixel_rays(1)
    q0 = kin.Q_READY
    tip0 = kin.fk(q0)
    tip0[:3, 3] *= 1000.0
    # the camera looks at the flange's ready position from 700 mm
    T_bc = look_at(tip0[:3, 3] + np.array([450.0, -350.0, 400.0]), tip0[:3, 3], np.array([0.0, 0.0, 1.0]))
    # board on a bracket on the flange, facing away from the tool (towards the camera above)
    T_tb = make_transform(_rot(np.pi, 0, 0.3), [-60.0, -40.0, 60.0])
    job = HandEyeJob(cam, pattern=PATTERN, square_mm=SQUARE, min_views=8)
    rng = np.random.default_rng(5)
    accepted = refused = 0
    for _ in range(80):
        if accepted >= 12:
            break
        q = q0 + rng.uniform(-0.3, 0.3, 6) * np.array([1, 0.5, 0.5, 1.2, 1.2, 1.2])
        Tb = kin.fk(q)
        Tb[:3, 3] *= 1000.0
        T_cam_board = invert_transform(T_bc) @ Tb @ T_tb
        corners = np.array([[0, 0, 0], [(PATTERN[0] + 1) * SQUARE, 0, 0], [0, (PATTERN[1] + 1) * SQUARE, 0],
                            [(PATTERN[0] + 1) * SQUARE, (PATTERN[1] + 1) * SQUARE, 0]]) - SQUARE
        pc = corners @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
        if np.any(pc[:, 2] < 200) or T_cam_board[:3, 2] @ T_cam_board[:3, 3] > -0.3 * np.linalg.norm(T_cam_board[:3, 3]):
            continue  # behind the camera or facing away
        px = cam.project(pc)
        if np.any(px < 5) or np.any(px[:, 0] > 1275) or np.any(px[:, 1] > 715):
            continue
        r = job.add_view(Tb, render_chessboard(cam, T_cam_board, PATTERN, SQUARE, supersample=1, rays=rays))
        accepted += r.accepted
        refused += not r.accepted
    assert accepted >= 8, (accepted, refused)
    res = job.solve()
    assert res.ok, res.reason
    assert np.linalg.norm(res.T_base_cam_mm[:3, 3] - T_bc[:3, 3]) < 2.0
    assert rotation_angle_deg(res.T_base_cam_mm[:3, :3], T_bc[:3, :3]) < 0.2
    assert res.translation_rms_mm < 1.0 and res.rotation_rms_deg < 0.2
    # the same pose twice is refused: no new information
    v = job.views[0]
    r = job.add_view(v.T_base_tool_mm, render_chessboard(cam, invert_transform(T_bc) @ v.T_base_tool_mm @ T_tb,
                                                         PATTERN, SQUARE, supersample=1, rays=rays))
    assert not r.accepted and "rotate the wrist" in r.reason


def test_jobs_capture_from_the_live_session(fresh_home):
    """capture(session) takes the newest camera frame (and the arm's pose): the twin's camera sees
    a head, not a board, so the view is refused with the reason; no arm -> a clear error."""
    from monotracker.engine import Session, SessionConfig

    s = Session(SessionConfig(home=fresh_home, camera="sim", clock="sim"))
    try:
        with pytest.raises(InputError, match="start the camera"):
            IntrinsicsJob().capture(s)
        assert s.start_camera().ok
        s.advance(0.2)
        r = IntrinsicsJob(pattern=(9, 6)).capture(s)
        assert not r.accepted and "no 9x6 chessboard found" in r.reason
        cam = CameraModel(s.snapshot().camera.K, s.snapshot().camera.dist, s.snapshot().camera.image_size)
        with pytest.raises(InputError, match="connect the arm"):
            HandEyeJob(cam).capture(s)
    finally:
        s.shutdown()
