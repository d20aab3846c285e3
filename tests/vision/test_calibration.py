"""Calibration from synthetic chessboard images rendered by our own ray-plane projection."""

import subprocess
import sys

import cv2
import numpy as np
import pytest

from monotracker.errors import InputError
from monotracker.geometry import make_transform, rotation_about_axis
from monotracker.vision.calibration import calibrate_chessboard, parse_pattern, render_chessboard
from monotracker.vision.camera_model import CameraModel

TRUE = CameraModel(np.array([[610.0, 0, 322.5], [0, 608.0, 236.0], [0, 0, 1]]),
                   np.array([-0.21, 0.06, 0.0, 0.0, 0.0]), (640, 480))
PATTERN = (9, 6)
SQUARE = 20.0


@pytest.fixture(scope="module")
def board_images():
    rays = TRUE.pixel_rays(2)
    rng = np.random.default_rng(7)
    imgs = []
    for _i in range(12):
        ax = rng.normal(size=3)
        R = rotation_about_axis(ax, np.radians(rng.uniform(10, 35)))
        centre = np.array([(PATTERN[0] - 1) * SQUARE / 2, (PATTERN[1] - 1) * SQUARE / 2, 0])
        t = np.array([rng.uniform(-60, 60), rng.uniform(-40, 40), rng.uniform(330, 480)]) - R @ centre
        imgs.append(render_chessboard(TRUE, make_transform(R, t), PATTERN, SQUARE, rays=rays))
    return imgs


def test_chessboard_calibration_recovers_intrinsics(board_images):
    res = calibrate_chessboard(board_images, PATTERN, SQUARE)
    K = res.camera.K
    assert res.rms_px < 0.3
    assert abs(K[0, 0] - 610) / 610 < 0.01 and abs(K[1, 1] - 608) / 608 < 0.01
    assert abs(K[0, 2] - 322.5) < 3 and abs(K[1, 2] - 236) < 3
    assert abs(res.camera.dist[0] - (-0.21)) < 0.03
    # the fitted model reprojects like the true one over the image (< 0.5 px)
    pts = np.array([[x, y, 500.0] for x in (-200, 0, 150) for y in (-150, 0, 120)])
    assert np.abs(res.camera.project(pts) - TRUE.project(pts)).max() < 0.5
    assert res.camera.image_size == (640, 480)


def test_too_few_views_and_bad_pattern(board_images):
    blank = [np.full((480, 640), 128, np.uint8)] * 3
    with pytest.raises(InputError, match="usable calibration views"):
        calibrate_chessboard(blank + board_images[:1], PATTERN, SQUARE)
    with pytest.raises(InputError, match="COLSxROWS"):
        parse_pattern("nine by six")


def test_cli_calibrate_camera(tmp_path, board_images):
    paths = []
    for i, im in enumerate(board_images[:8]):
        p = tmp_path / f"b{i}.png"
        cv2.imwrite(str(p), im)
        paths.append(str(p))
    out = tmp_path / "cam.json"
    r = subprocess.run([sys.executable, "-m", "monotracker", "calibrate-camera", *paths, "--chessboard", "9x6",
                        "--square-mm", "20", "--out", str(out)], capture_output=True, text=True, cwd=tmp_path,
                       env={"PYTHONPATH": str(__import__("monotracker").__path__[0].rsplit("/", 1)[0]),
                            "MONOTRACKER_HOME": str(tmp_path)})
    assert r.returncode == 0, r.stderr
    assert "RMS reprojection error" in r.stdout
    cam = CameraModel.load(out)
    assert abs(cam.K[0, 0] - 610) < 10
    # f ~ 610 px images the kit's 4 mm balls at ~6.1 px from 400 mm: the lens is named as short
    notes = [ln for ln in r.stdout.splitlines() if ln.startswith("note: short lens")]
    assert len(notes) == 1 and " 6.1 px" in notes[0], r.stdout
    # wrong board size: a clear one-line error, exit code 2
    r = subprocess.run([sys.executable, "-m", "monotracker", "calibrate-camera", *paths[:4], "--chessboard", "7x4",
                        "--square-mm", "20"], capture_output=True, text=True, cwd=tmp_path,
                       env={"PYTHONPATH": str(__import__("monotracker").__path__[0].rsplit("/", 1)[0]),
                            "MONOTRACKER_HOME": str(tmp_path)})
    assert r.returncode == 2 and r.stderr.startswith("error:") and len(r.stderr.strip().splitlines()) == 1


def test_charuco_calibration():
    from monotracker.vision.calibration import calibrate_charuco, render_board_texture

    squares, sq, mk = (7, 5), 30.0, 22.0
    board = cv2.aruco.CharucoBoard(squares, sq, mk, cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100))
    ppm = 6  # texture px per mm
    tex = board.generateImage((int(squares[0] * sq * ppm), int(squares[1] * sq * ppm)), marginSize=0)
    tex = cv2.copyMakeBorder(tex, 60, 60, 60, 60, cv2.BORDER_CONSTANT, value=255)
    rays = TRUE.pixel_rays(2)
    rng = np.random.default_rng(3)
    imgs = []
    for _i in range(8):
        R = rotation_about_axis(rng.normal(size=3), np.radians(rng.uniform(10, 30)))
        centre = np.array([squares[0] * sq / 2 + 10, squares[1] * sq / 2 + 10, 0])
        t = np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), rng.uniform(380, 480)]) - R @ centre
        imgs.append(render_board_texture(TRUE, make_transform(R, t), tex, 1.0 / ppm, rays=rays))
    res = calibrate_charuco(imgs, squares, sq, mk)
    assert res.rms_px < 0.5 and len(res.per_view_rms_px) >= 6
    assert abs(res.camera.K[0, 0] - 610) / 610 < 0.02 and abs(res.camera.K[1, 1] - 608) / 608 < 0.02
    with pytest.raises(InputError, match="smaller than the square"):
        calibrate_charuco(imgs, squares, sq, 40.0)
