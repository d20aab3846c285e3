"""Projection honours every OpenCV distortion model (independent truth: cv2.projectPoints)."""

import cv2
import numpy as np
import pytest

from monotracker.registration.projection import project_pixels, undistort_to_normalised

K = np.array([[1100.0, 0.0, 641.3], [0.0, 1098.0, 358.2], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("dist", [
    np.array([-0.12, 0.09, 0.0004, -0.0003]),
    np.array([-0.12, 0.09, 0.0004, -0.0003, 0.01]),
    np.array([-0.1, 0.05, 0.001, 0.0, 0.01, 0.02, 0.003, 0.001]),          # rational
    np.array([-0.1, 0.05, 0.001, 0.0, 0.01, 0.02, 0.003, 0.001, 1e-3, -1e-3, 2e-3, 5e-4]),  # thin prism
])
def test_projection_matches_opencv_and_inverts_undistortion(dist):
    rng = np.random.default_rng(1)
    X = np.column_stack([rng.uniform(-150, 150, 40), rng.uniform(-90, 90, 40), rng.uniform(400, 700, 40)])
    ours = project_pixels(X, K, dist)
    ref, _ = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=1e-9)
    back = undistort_to_normalised(ours, K, dist)
    np.testing.assert_allclose(back, X[:, :2] / X[:, 2:], atol=1e-9)
