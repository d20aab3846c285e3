"""Camera model files and validation."""

import json

import cv2
import numpy as np
import pytest

from monotracker.errors import InputError
from monotracker.vision.camera_model import CameraModel, default_camera


@pytest.mark.parametrize("suffix", [".yml", ".yaml", ".xml", ".json"])
def test_roundtrip(tmp_path, suffix):
    cam = default_camera()
    p = cam.save(tmp_path / f"cam{suffix}")
    back = CameraModel.load(p)
    assert np.allclose(back.K, cam.K) and np.allclose(back.dist, cam.dist) and back.image_size == (1280, 720)


def test_reads_opencv_written_yaml(tmp_path):
    """A file written by OpenCV itself (as its calibration sample does) is read."""
    p = str(tmp_path / "opencv.yml")
    fs = cv2.FileStorage(p, cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[0.1, -0.05, 0, 0, 0]]))
    fs.release()
    cam = CameraModel.load(p)
    assert cam.K[0, 0] == 500 and cam.dist[0] == pytest.approx(0.1) and cam.image_size == (640, 480)


def test_project_matches_opencv():
    cam = default_camera()
    pts = np.array([[10.0, -20, 500], [-60, 30, 450], [0, 0, 600]])
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.allclose(cam.project(pts), ref.reshape(-1, 2), atol=1e-9)
    xn = cam.undistort_points(cam.project(pts))
    assert np.allclose(xn, pts[:, :2] / pts[:, 2:], atol=1e-8)


@pytest.mark.parametrize("content, needle", [
    ("not json at all", "not valid JSON"),
    (json.dumps({"foo": 1}), "lacks camera_matrix"),
    (json.dumps({"camera_matrix": [[1, 0], [0, 1]], "distortion_coefficients": [0, 0, 0, 0, 0],
                 "image_width": 640, "image_height": 480}), "3x3"),
    (json.dumps({"camera_matrix": [[-500, 0, 320], [0, 500, 240], [0, 0, 1]], "distortion_coefficients": [0] * 5,
                 "image_width": 640, "image_height": 480}), "focal"),
    (json.dumps({"camera_matrix": [[500, 0, 320], [0, 500, 240], [0, 0, 1]], "distortion_coefficients": [0] * 5,
                 "image_width": 200, "image_height": 100}), "principal point"),
    (json.dumps({"camera_matrix": [[500, 0, 320], [0, 500, 240], [0, 0, 1]], "distortion_coefficients": [0] * 3,
                 "image_width": 640, "image_height": 480}), "4, 5, 8"),
])
def test_wrong_calibration_file_gives_clear_error(tmp_path, content, needle):
    p = tmp_path / "cam.json"
    p.write_text(content)
    with pytest.raises(InputError) as e:
        CameraModel.load(p)
    assert needle in str(e.value) and "\n" not in str(e.value)


def test_wrong_yaml_and_missing_file(tmp_path):
    p = tmp_path / "cam.yml"
    p.write_text("%YAML:1.0\n---\nsomething_else: 3\n")
    with pytest.raises(InputError, match="lacks camera_matrix"):
        CameraModel.load(p)
    q = tmp_path / "garbage.yml"
    q.write_bytes(b"\x00\x01 not yaml {{{")
    with pytest.raises(InputError, match="cam|garbage"):
        CameraModel.load(q)
    with pytest.raises(InputError, match="not found"):
        CameraModel.load(tmp_path / "nope.yml")
