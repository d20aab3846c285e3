"""The shared overlay stream draws on the frame already downscaled for display: every mark lands
where the camera-pixel truth says it should (scaled), as when drawing on the full frame first."""

from __future__ import annotations

from types import SimpleNamespace as NS

import cv2
import numpy as np


def _scene():
    K = np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0, 0, 400.0]
    centres = np.array([[0.0, 0, 0], [60, 0, 0], [0, 60, 0], [-60, -30, 0]])
    fids = tuple(NS(id=i, centre_lps_mm=c, radius_mm=4.0, status="confirmed") for i, c in enumerate(centres))
    status = {0: "seen", 1: "seen", 2: "seen", 3: "occluded"}
    pose = NS(trusted=True, reason="", T_cam_ct=T, fiducial_status=status, residuals_px={}, fre_mm=0.1,
              predicted_tre_mm=0.5)
    snap = NS(pose=pose, camera=NS(K=K, dist=None), fiducials=fids, plan=NS(entry_lps_mm=None, target_lps_mm=None))
    return K, T, centres, status, snap


def test_marks_at_display_scale_match_camera_pixels():
    from monotracker.ui.overlay import GREEN, RED, project_points
    from monotracker.ui.stream import OverlayStream

    K, T, centres, status, snap = _scene()
    uv = project_points(centres, T, K)  # camera px (1280x720 frame), hand-checkable: 640 + 900*x/400
    assert np.allclose(uv[1], [640 + 900 * 60 / 400, 360])
    est = NS(T_cam_ct=T, status=list(status.values()), image_points_px=uv, residuals_px=np.full(4, np.nan))
    frame = np.full((720, 1280, 3), 90, np.uint8)
    stream = OverlayStream(display_width=640)
    out = cv2.imdecode(np.frombuffer(stream.encode_frame(frame, est, snap), np.uint8), cv2.IMREAD_COLOR)
    assert out.shape == (360, 640, 3)
    s = 0.5
    for j in (0, 1, 2):  # a green dot at each detected centre, scaled to the display
        u, v = np.round(uv[j] * s).astype(int)
        patch = out[v - 1:v + 2, u - 1:u + 2].reshape(-1, 3).astype(int)
        assert np.all(np.abs(patch - GREEN).max(axis=1) < 60), (j, patch)
    u, v = np.round(uv[3] * s).astype(int)  # the hidden one: a red ring around its place, not a dot
    ring = out[v - 12:v + 13, u - 12:u + 13].reshape(-1, 3).astype(int)
    assert np.any(np.abs(ring - RED).max(axis=1) < 60)
    assert np.abs(out[v, u].astype(int) - GREEN).max() > 60
    assert frame.mean() == 90  # the camera frame itself is never drawn on
