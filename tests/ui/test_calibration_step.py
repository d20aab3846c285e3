"""The Calibrate step (reached from Register) driven end to end in headless Chromium: camera
intrinsics from boards the live camera shows, then hand-eye with the simulated UR10.

The simulated camera renders the patient's head, never a calibration board, so this test gives
the session a camera (through ``Session(camera_factory=...)``, the engine's hook for test
doubles) that is the normal simulated rig whose frames are replaced by chessboards rendered by
our own ray-plane renderer (``vision.calibration.render_chessboard``, with the sim camera's real
lens distortion). The frames flow through the engine's camera loop as any frame does, and the
page's "Capture view" takes the newest one (``IntrinsicsJob.capture``). For hand-eye the arm is
moved by the test (the simulated arm's joints set directly, as an operator moves a real arm in
freedrive) and the board on the flange is rendered from the arm's true flange pose and a camera
pose the test chose; the solve must recover that pose. Truths are independent of the page: the
sim camera's intrinsics and the chosen camera pose.
"""

from __future__ import annotations

import numpy as np
import pytest
from browser_helpers import _click, _command, _input, _take_control, _wait, open_page, served_locked_sample

pytestmark = pytest.mark.timeout(900)

PATTERN, SQUARE = (7, 5), 20.0


class BoardFeed:
    """The image the test camera shows now (None: the normal simulated frame)."""

    def __init__(self):
        self.image = None
        self.rigs = []


def _board_rig_factory(feed: BoardFeed):
    from monotracker.engine.rigs.sim import SimImageRig

    class BoardRig(SimImageRig):
        # the board replaces the rendered image before the frame becomes the newest one: swapped
        # after it (as this test once did), a capture could read the head in between and report
        # "no chessboard found" for a board in view (seen beside CPU load)
        def _new_frame(self, img, t, truth):
            board = feed.image
            if board is not None:
                img = np.repeat(board[:, :, None], 3, axis=2) if board.ndim == 2 else board.copy()
            return super()._new_frame(img, t, truth)

    def factory(source, calibration_path, plan, cfg, session):
        rig = BoardRig(plan, trajectory=cfg.trajectory, seed=cfg.seed, fps=cfg.camera_fps)
        rig.clock = session.clock
        feed.rigs.append(rig)
        return rig

    return factory


def _rot(rx, ry, rz):
    import cv2

    R, _ = cv2.Rodrigues(np.array([rx, ry, rz], float))
    return R


def _intrinsic_board_poses(cam, rng, n):
    """Board poses (T_cam_board, mm) whose board fills a third to a half of the image, spread
    over it, tilted up to ~35 deg."""
    from monotracker.geometry import make_transform

    w, h = cam.image_size
    f = cam.K[0, 0]
    board_w = (PATTERN[0] + 1) * SQUARE
    out = []
    for k in range(n):
        z = f * board_w / (rng.uniform(0.35, 0.5) * w)
        R = _rot(*rng.uniform(-0.6, 0.6, 2), rng.uniform(-0.4, 0.4)) if k else np.eye(3)
        c = np.array([rng.uniform(-0.22, 0.22) * w * z / f, rng.uniform(-0.22, 0.22) * h * z / f, z])
        centre = np.array([(PATTERN[0] - 1) * SQUARE / 2, (PATTERN[1] - 1) * SQUARE / 2, 0])
        out.append(make_transform(R, c - R @ centre))
    return out


def _show(feed, s, image):
    """Put ``image`` on the camera and wait until the engine has a frame made after the swap."""
    fr = s.latest_frame()
    i0 = -1 if fr is None else fr[1]
    feed.image = image
    _wait(lambda: (f := s.latest_frame()) is not None and f[1] >= i0 + 2, what="a new camera frame")


def _server_field(app, handle_name, value):
    """Wait until this test's tab's field holds ``value`` on the server (typed values arrive
    asynchronously)."""
    def ok():
        views = app.views()
        return views and all(getattr(v.steps["calibration"], handle_name).value == value for v in views)

    _wait(ok, what=f"{handle_name} = {value!r} on the server")


def _set(page, app, label, handle_name, text, value):
    box = _input(page, label)
    box.fill(text)
    box.press("Tab")
    _server_field(app, handle_name, value)


@pytest.fixture
def served(tmp_path, monkeypatch, port):
    feed = BoardFeed()
    # the sim arm in this process (the test moves it); the camera at 15 fps, not 30: the test
    # shows boards and checks the page's calibration, not the pose rate, and half the frames
    # leave the browser CPU on 2 cores (issue 35; 15 fps stays above the 0.1 s freeze gate)
    config = dict(camera="sim", trajectory="still", control_process=False, camera_fps=15.0)
    with served_locked_sample(tmp_path, monkeypatch, port, config, camera_factory=_board_rig_factory(feed)) as (s, app):
        yield s, app, feed


def test_calibration_step_in_browser(served, browser, artifacts, tmp_path):
    from monotracker.geometry import invert_transform, look_at, make_transform, rotation_angle_deg
    from monotracker.vision.calibration import render_chessboard
    from monotracker.vision.camera_model import CameraModel

    s, app, feed = served
    page = open_page(browser, app)
    page.get_by_role("button", name="Take control (PIN)").wait_for()
    assert "in control" in _take_control(page, "2468")
    _click(page, "3 Register")
    assert "camera started" in _command(page, "Start camera")
    _wait(lambda: s.latest_frame() is not None, what="first frame")
    _click(page, "Calibrate camera / hand-eye")
    page.get_by_role("button", name="Capture view").wait_for()

    # ---------------------------------------------------------------- intrinsics
    truth = feed.rigs[-1].camera_model  # the simulated camera's real intrinsics and distortion
    _set(page, app, "Corners / squares (cols x rows)", "h_pattern", "7x5", "7x5")
    _set(page, app, "Square (mm)", "h_square", "20", 20.0)
    _set(page, app, "Views needed", "h_min", "8", 8)
    # no board in view: refused with the reason, nothing taken
    msg = _command(page, "Capture view")
    assert "refused" in msg and "no 7x5 chessboard found" in msg, msg
    page.wait_for_function("document.querySelector('#mt-cal-last') && "
                           "document.querySelector('#mt-cal-last').dataset.accepted === '0'")
    # boards drawn with 2x2 samples a pixel: drawn with one, their aliased corners biased the solved
    # principal point by 2-4 px depending on which views were taken (the same 12 boards solved
    # offline: 3.1-3.7 px off with one sample, 0.0-0.6 px with four), which once crossed the
    # 4 px check below in CI
    rays = truth.pixel_rays(2)
    rng = np.random.default_rng(11)
    poses = _intrinsic_board_poses(truth, rng, 12)
    accepted = 0
    for k, T in enumerate(poses):
        _show(feed, s, render_chessboard(truth, T, PATTERN, SQUARE, supersample=2, rays=rays))
        msg = _command(page, "Capture view")
        accepted += "Capture view: accepted" in msg
        if k == 0:  # the same board again: a duplicate, refused with the reason
            assert "accepted" in msg, msg
            dup = _command(page, "Capture view")
            assert "refused" in dup and "too close" in dup, dup
    assert accepted >= 8, accepted
    page.wait_for_function(f"document.querySelector('#mt-cal-coverage').dataset.views === '{accepted}' && "
                           "document.querySelector('#mt-cal-coverage').dataset.ready === '1'")
    assert float(page.locator("#mt-cal-coverage").get_attribute("data-coverage")) > 0.5
    msg = _command(page, "Solve intrinsics")
    assert "Solve intrinsics: RMS" in msg, msg
    page.locator("#mt-cal-intr").wait_for()
    rms_page = float(page.locator("#mt-cal-intr").get_attribute("data-rms"))
    assert rms_page < 0.5
    assert page.locator("#mt-cal-intr ~ table tr").count() == accepted + 1  # per-view errors
    # saving: a bad folder is one line; a good path writes a camera file that loads back
    _set(page, app, "Save camera to", "h_cam_path", "/no/such/dir/cam.yaml", "/no/such/dir/cam.yaml")
    msg = _command(page, "Save camera calibration")
    assert "folder not found" in msg and "Traceback" not in page.content()
    cam_path = str(tmp_path / "cam.yaml")
    _set(page, app, "Save camera to", "h_cam_path", cam_path, cam_path)
    msg = _command(page, "Save and use for this camera")
    assert "now uses it" in msg, msg
    solved = CameraModel.load(cam_path)
    K, K0 = solved.K, truth.K
    assert abs(K[0, 0] - K0[0, 0]) < 0.01 * K0[0, 0] and abs(K[1, 1] - K0[1, 1]) < 0.01 * K0[1, 1]
    assert abs(K[0, 2] - K0[0, 2]) < 4 and abs(K[1, 2] - K0[1, 2]) < 4, (accepted, rms_page, K, K0)
    _wait(lambda: s.snapshot().camera.calibration_path == cam_path and s.snapshot().camera.running,
          what="the camera restarted with the saved calibration")
    page.screenshot(path=str(artifacts / "calibration_intrinsics.png"), full_page=True)

    # ---------------------------------------------------------------- hand-eye
    _show(feed, s, None)  # the head again: no board in view
    msg = _command(page, "Record pose + view")  # connects the arm (disarmed); no board yet
    assert "refused" in msg and "chessboard found" in msg, msg
    assert s.snapshot().robot.connected and s.snapshot().robot.state == "disarmed"
    robot = s._loop.robot.rig  # test-only: move the simulated arm (an operator's freedrive)
    arm = robot.sim_arm
    q0 = np.array(arm.true_q)

    def tip():
        return np.asarray(robot.status().T_base_tip, float)

    tip0 = tip()
    T_bc = look_at(tip0[:3, 3] + np.array([450.0, -350.0, 400.0]), tip0[:3, 3], np.array([0.0, 0.0, 1.0]))
    T_tb = make_transform(_rot(np.pi, 0, 0.3), [-60.0, -40.0, 60.0])  # board on a bracket on the flange
    w, h = truth.image_size
    rng = np.random.default_rng(5)
    he_accepted = 0
    for _ in range(200):
        if he_accepted >= 10:
            break
        q = q0 + rng.uniform(-0.3, 0.3, 6) * np.array([1, 0.5, 0.5, 1.2, 1.2, 1.2])
        with arm._lock:
            arm.true_q = q.copy()
            arm.true_dq = np.zeros(6)
        _wait(lambda q=q: np.allclose(robot.status().q, q), what="arm moved")
        T_cam_board = invert_transform(T_bc) @ tip() @ T_tb
        corners = np.array([[0, 0, 0], [(PATTERN[0] + 1) * SQUARE, 0, 0], [0, (PATTERN[1] + 1) * SQUARE, 0],
                            [(PATTERN[0] + 1) * SQUARE, (PATTERN[1] + 1) * SQUARE, 0]]) - SQUARE
        pc = corners @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
        if np.any(pc[:, 2] < 200) or T_cam_board[:3, 2] @ T_cam_board[:3, 3] > -0.3 * np.linalg.norm(T_cam_board[:3, 3]):
            continue  # behind the camera or facing away
        px = truth.project(pc)
        if np.any(px < 5) or np.any(px[:, 0] > w - 5) or np.any(px[:, 1] > h - 5):
            continue
        _show(feed, s, render_chessboard(truth, T_cam_board, PATTERN, SQUARE, supersample=2, rays=rays))
        msg = _command(page, "Record pose + view")
        he_accepted += "Record pose: accepted" in msg
    assert he_accepted >= 8, he_accepted
    page.wait_for_function(f"document.querySelector('#mt-cal-poses').dataset.views === '{he_accepted}'")
    msg = _command(page, "Solve hand-eye")
    assert "Solve hand-eye: residual RMS" in msg, msg
    page.locator("#mt-cal-he[data-ok='1']").wait_for()
    assert float(page.locator("#mt-cal-he").get_attribute("data-mm")) < 2.0
    he_path = str(tmp_path / "he.json")
    _set(page, app, "Save hand-eye to", "h_he_path", he_path, he_path)
    msg = _command(page, "Save and apply hand-eye")
    assert "applied to the session" in msg, msg
    from monotracker.robot.handeye import load_handeye

    saved = load_handeye(he_path)
    T_saved = np.asarray(getattr(saved, "T_base_cam_mm", saved), float)
    T_plan = np.asarray(s.plan_copy().T_base_cam, float)
    assert np.allclose(T_plan, T_saved)
    # against the truth the test chose. The intrinsics are this page's own solve (fx within 1 %),
    # not the truth, with the camera ~750 mm away: measured 3.5 mm here (the engine test with the
    # true intrinsics gets < 2 mm)
    assert np.linalg.norm(T_plan[:3, 3] - T_bc[:3, 3]) < 5.0
    assert rotation_angle_deg(T_plan[:3, :3], T_bc[:3, :3]) < 0.5
    page.screenshot(path=str(artifacts / "calibration_handeye.png"), full_page=True)
    assert "Traceback" not in page.content()
    page.close()


def test_viewing_tab_cannot_apply_calibration(served, browser):
    """A tab not in control may look but cannot connect the arm or change the session camera."""
    s, app, feed = served
    page = open_page(browser, app)
    page.get_by_role("button", name="Take control (PIN)").wait_for()
    _click(page, "3 Register")
    _click(page, "Calibrate camera / hand-eye")
    page.get_by_role("button", name="Record pose + view").wait_for()
    msg = _command(page, "Record pose + view")
    assert "cannot connect the arm" in msg and "control" in msg, msg
    assert s.robot_status() is None
    msg = _command(page, "Save and use for this camera")
    assert "solve the calibration before saving it" in msg
    page.close()

