"""Validation-fiducial error (point to viewing ray), against independently built image points
(the simulator's own tangent-cone ellipse centres and OpenCV's distortion)."""

import numpy as np

from monotracker.registration.validation import match_detections, validate
from monotracker.sim.scenes import _to_pixels, default_K, ellipse_centre_normalised

K = default_K(1100.0, (1280, 720))
DIST = np.array([-0.06, 0.02, 0.0, 0.0, 0.0])
R = 4.0


def _pose():
    a = np.radians(25)
    Rm = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    T = np.eye(4)
    T[:3, :3] = Rm
    T[:3, 3] = [10.0, -20.0, 480.0]
    return T


def _image(T, X):
    Xc = X @ T[:3, :3].T + T[:3, 3]
    return _to_pixels(ellipse_centre_normalised(Xc, R), K, DIST)


X = np.array([[60.0, 20.0, 10.0], [-70.0, 35.0, 5.0], [0.0, -80.0, 15.0]])


def test_exact_pose_gives_zero_error_and_a_known_offset_gives_that_offset():
    T = _pose()
    px = _image(T, X)
    r = validate(T, [7, 8, 9], X, px, K, DIST, R, limit_mm=1.5)
    assert r.ok and max(r.errors_mm.values()) < 1e-6
    # the pose's translation moved 1.2 mm across the line of sight of fiducial 7 (perpendicular to its ray)
    Xc = X[0] @ T[:3, :3].T + T[:3, 3]
    ray = Xc / np.linalg.norm(Xc)
    perp = np.cross(ray, [0.0, 1.0, 0.0])
    perp /= np.linalg.norm(perp)
    T2 = T.copy()
    T2[:3, 3] += 1.2 * perp
    r2 = validate(T2, [7, 8, 9], X, px, K, DIST, R, limit_mm=1.5)
    assert abs(r2.errors_mm[7] - 1.2) < 0.01
    # ...and 2 mm fails the 1.5 mm limit with a reason naming the worst fiducial
    T3 = T.copy()
    T3[:3, 3] += 2.0 * perp
    r3 = validate(T3, [7, 8, 9], X, px, K, DIST, R, limit_mm=1.5)
    assert not r3.ok and "validation fiducial 7" in r3.reason and abs(r3.errors_mm[7] - 2.0) < 0.02


def test_depth_error_is_not_observable_from_one_view():
    T = _pose()
    px = _image(T, X)
    Xc = X[0] @ T[:3, :3].T + T[:3, 3]
    T2 = T.copy()
    T2[:3, 3] += 2.0 * Xc / np.linalg.norm(Xc)  # along fiducial 7's ray
    r = validate(T2, [7], X[:1], px[:1], K, DIST, R, limit_mm=1.5)
    assert r.errors_mm[7] < 0.05  # a lower bound, as documented


def test_unseen_validation_fiducial_fails_and_used_or_far_blobs_are_ignored():
    T = _pose()
    px = _image(T, X)
    # fiducial 9's blob missing; a stray 200 px away; blob of 8 claimed by the registration
    det = np.vstack([px[0], px[1], px[2] + 200.0])
    r = validate(T, [7, 8, 9], X, det, K, DIST, R, limit_mm=1.5, used_px=px[1:2])
    assert not r.ok and r.errors_mm[9] is None and r.errors_mm[8] is None and "not seen" in r.reason
    m = match_detections(T, X, det, K, DIST, R)
    assert np.allclose(m[0], px[0]) and np.all(np.isnan(m[2]))
    assert validate(T, [], np.zeros((0, 3)), det, K, DIST, R, 1.5).ok
