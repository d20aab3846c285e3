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


# ---------------------------------------------------------------- absurd values: one line, never a crash
_GOOD = {"camera_matrix": [[1100, 0, 640], [0, 1100, 360], [0, 0, 1]],
         "distortion_coefficients": [-0.1, 0.05, 0, 0, 0], "image_width": 1280, "image_height": 720}


@pytest.mark.parametrize("change, needles", [
    # a focal length a million times too long: the field of view (0.00007 deg) says what is wrong
    ({"camera_matrix": [[1e9, 0, 640], [0, 1e9, 360], [0, 0, 1]]}, ("fx=1e+09", "field of view", "in pixels")),
    # focal lengths in mm (4 mm lens): a 179 deg field of view
    ({"camera_matrix": [[4, 0, 640], [0, 4, 360], [0, 0, 1]]}, ("fx=4 px", "field of view")),
    # k1 = 50: the image is stretched ~6x towards its edges
    ({"distortion_coefficients": [50, 0, 0, 0, 0]}, ("distortion_coefficients (50", "stretch", "order k1")),
    # a model that folds over inside the image (r(1 + k1 r^2) turns back before the corner)
    ({"distortion_coefficients": [-2.5, 0, 0, 0, 0]}, ("distortion_coefficients (-2.5", "inverted")),
    ({"image_width": float("inf")}, ("image_width", "finite whole number")),
    ({"image_height": float("nan")}, ("image_height", "finite whole number")),
    ({"image_width": 1e12}, ("image_width", "outside 1-20000")),
    ({"image_width": 1280.5}, ("image_width 1280.5", "whole number")),
])
def test_absurd_calibration_values_give_one_clear_line(tmp_path, change, needles):
    """Before: fx = 1e9 and k1 = 50 loaded (and tracking failed later with a line about the
    head's distance or missing balls); image_width = inf crashed with OverflowError."""
    p = tmp_path / "cam.json"
    p.write_text(json.dumps({**_GOOD, **change}))          # json writes inf/nan as Infinity/NaN
    with pytest.raises(InputError) as e:
        CameraModel.load(p)
    msg = str(e.value)
    assert all(n in msg for n in needles), msg
    assert msg.startswith("camera file cam.json: ") and "\n" not in msg


def test_infinite_image_width_in_opencv_yaml_is_one_line(tmp_path):
    p = tmp_path / "cam.yml"
    p.write_text("%YAML:1.0\n---\nimage_width: .inf\nimage_height: 720\n"
                 "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
                 "   data: [ 1100., 0., 640., 0., 1100., 360., 0., 0., 1. ]\n"
                 "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
                 "   data: [ 0., 0., 0., 0., 0. ]\n")
    with pytest.raises(InputError, match="image_width is inf"):
        CameraModel.load(p)
    with pytest.raises(InputError, match="image width is inf"):
        CameraModel(np.array(_GOOD["camera_matrix"], float), np.zeros(5), (float("inf"), 720))


@pytest.mark.parametrize("K, dist, size", [
    # OpenCV's sample stereo camera (samples/data, left): strong barrel + k3
    ([[535.9, 0, 342.3], [0, 535.9, 235.6], [0, 0, 1]], [-0.2664, -0.0386, 0.00178, -0.00028, 0.2384], (640, 480)),
    # a wide-angle camera (~95 deg horizontal, strong barrel that still reaches the corners)
    ([[700, 0, 640], [0, 700, 360], [0, 0, 1]], [-0.28, 0.08, 0, 0, 0], (1280, 720)),
    # OpenCV's rational model (8 coefficients)
    ([[900, 0, 960], [0, 900, 540], [0, 0, 1]], [0.8, 0.2, 0.0, 0.0, 0.01, 1.1, 0.35, 0.02], (1920, 1080)),
    # a wide lens whose fitted polynomial turns back ~60 px inside the left and right edges
    ([[600, 0, 640], [0, 600, 360], [0, 0, 1]], [-0.3, 0.08, 0, 0, -0.01], (1280, 720)),
    # a long lens: 5 deg
    ([[14000, 0, 640], [0, 14000, 360], [0, 0, 1]], [0.3, 0, 0, 0, 0], (1280, 720)),
])
def test_real_lenses_still_load(tmp_path, K, dist, size):
    """The new limits refuse no ordinary calibration (wide-angle, rational model, telephoto, a
    wide lens whose polynomial folds near the corners: see test_sphere_outline)."""
    p = tmp_path / "cam.json"
    p.write_text(json.dumps({"camera_matrix": K, "distortion_coefficients": dist,
                             "image_width": size[0], "image_height": size[1]}))
    cam = CameraModel.load(p)
    assert cam.image_size == size
