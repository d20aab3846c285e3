"""Camera projection helpers for registration, in the OpenCV camera frame (x right, y down,
z forward, mm).

All matching and refinement work on the *normalised image plane* (undistorted pixel
coordinates pushed through ``K^-1``): lens distortion is removed once from the measured
points (``undistort_to_normalised``), so every hypothesis is a plain pinhole projection.
Residuals reported in pixels are the normalised residuals multiplied by the focal lengths
(fx, fy): "equivalent pinhole pixels", which equal image pixels up to the local scale of the
distortion (< 2 % for ordinary lenses).

Sphere-centre bias (paper Eq. 4-6): a sphere of radius R with centre (a, b, c) in the camera
frame images as an ellipse whose centre on the normalised plane is exactly
``(a c, b c) / (c^2 - R^2)``, not ``(a, b) / c``. :func:`project_normalised` uses that model
when ``radius_mm`` is given, so the pose fit itself corrects the bias (no separate step).
"""

from __future__ import annotations

import cv2
import numpy as np


def undistort_to_normalised(points_px: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """(m, 2) pixel points -> (m, 2) undistorted normalised coordinates (x/z, y/z)."""
    pts = np.asarray(points_px, dtype=float).reshape(-1, 2)
    if len(pts) == 0:
        return pts.copy()
    if dist is None or not np.any(np.asarray(dist, dtype=float)):
        Kinv = np.linalg.inv(K)
        return pts @ Kinv[:2, :2].T + Kinv[:2, 2]
    out = cv2.undistortPointsIter(
        pts.reshape(-1, 1, 2), np.asarray(K, float), np.asarray(dist, float).ravel(), None, None,
        (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12),
    )
    return out.reshape(-1, 2)


def project_normalised(X_cam: np.ndarray, radius_mm: float | None = None) -> np.ndarray:
    """Normalised image coordinates of camera-frame points ``X_cam`` (..., 3) mm.

    With ``radius_mm`` the points are sphere centres and the exact ellipse centre
    ``(a c, b c) / (c^2 - R^2)`` is returned; otherwise the pinhole ``(a, b) / c``.
    """
    X = np.asarray(X_cam, dtype=float)
    c = X[..., 2]
    if radius_mm:
        denom = c * c - radius_mm * radius_mm
        s = c / denom
    else:
        s = 1.0 / c
    return X[..., :2] * s[..., None]


def distort_normalised(xy: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """Apply OpenCV's lens distortion to normalised points (..., 2) -> distorted normalised
    points (..., 2). Every model OpenCV calibrates is honoured (4, 5, 8, 12 or 14 coefficients:
    radial, tangential, rational, thin-prism, tilt), through ``cv2.projectPoints`` with identity
    intrinsics, so that projection and ``undistort_to_normalised`` are exact inverses."""
    xy = np.asarray(xy, dtype=float)
    if dist is None or not np.any(np.asarray(dist, dtype=float)):
        return xy
    flat = xy.reshape(-1, 2)
    if len(flat) == 0:
        return xy.copy()
    pts = np.column_stack([flat, np.ones(len(flat))]).reshape(-1, 1, 3)
    out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), np.asarray(dist, dtype=float).ravel())
    return out.reshape(xy.shape)


def normalised_to_pixels(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Normalised coordinates (..., 2) -> pixels with the intrinsics ``K`` (no distortion)."""
    xy = np.asarray(xy, dtype=float)
    return np.stack([K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2], K[1, 1] * xy[..., 1] + K[1, 2]], axis=-1)


def project_pixels(X_cam: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None,
                   radius_mm: float | None = None) -> np.ndarray:
    """Pixel positions of camera-frame points (sphere-bias model if ``radius_mm``)."""
    return normalised_to_pixels(distort_normalised(project_normalised(X_cam, radius_mm), dist), K)


def bearings(xy: np.ndarray) -> np.ndarray:
    """Unit viewing rays (..., 3) for normalised image points (..., 2)."""
    xy = np.asarray(xy, dtype=float)
    v = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)
