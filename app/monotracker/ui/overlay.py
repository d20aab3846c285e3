"""The registration overlay drawn on the live camera image (BGR uint8, pixels).

What the operator sees on each frame (nothing here decides anything; it draws what the engine's
pose estimate says):

* detected fiducial centres matched to a CT fiducial: filled green dot + the fiducial number;
* the CT fiducials reprojected with the estimated ``T_cam_ct`` (``cv2.projectPoints`` with the
  calibration ``K``, ``dist``): cyan ring, with the residual (px) between ring and dot;
* fiducials the estimate marks ``occluded``/``newly_lost``: a red ring at the reprojected place
  with "HIDDEN";
* the planned path projected (entry cyan cross -> target magenta);
* a banner along the top: green with FRE / predicted TRE / fiducials seen when the pose is
  valid, red with the reason when it is not.
"""

from __future__ import annotations

import cv2
import numpy as np

from monotracker.geometry import apply_transform
from monotracker.registration.projection import project_pixels

GREEN = (60, 200, 60)
CYAN = (255, 220, 0)
RED = (40, 40, 235)
MAGENTA = (255, 0, 255)
WHITE = (255, 255, 255)

HIDDEN = ("occluded", "newly_lost", "moved")


def project_points(points_ct: np.ndarray, T_cam_ct: np.ndarray, K: np.ndarray, dist=None) -> np.ndarray:
    """CT points (n, 3) mm -> pixels (n, 2) through ``T_cam_ct`` and the camera model (the
    registration's projection, full OpenCV distortion model). Points behind the camera come
    back as NaN."""
    p_cam = apply_transform(T_cam_ct, np.atleast_2d(np.asarray(points_ct, float)))
    if len(p_cam) == 0:
        return np.zeros((0, 2))
    uv = np.full((len(p_cam), 2), np.nan)
    front = p_cam[:, 2] > 0
    if front.any():
        uv[front] = project_pixels(p_cam[front], np.asarray(K, float), dist)
    return uv


def _finite(p) -> bool:
    return p is not None and bool(np.all(np.isfinite(p)))


def _ipt(p) -> tuple[int, int]:
    return int(round(float(p[0]))), int(round(float(p[1])))


def _text(img, s, org, colour, scale=0.7, thick=2):
    cv2.putText(img, s, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), thick + 3, cv2.LINE_AA)
    cv2.putText(img, s, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thick, cv2.LINE_AA)


def draw_overlay(image: np.ndarray, estimate, snap, *, in_place: bool = False, px_scale: float = 1.0) -> np.ndarray:
    """Draw the overlay for one frame. ``estimate``: vision's ``PoseEstimate`` for this frame
    (or None); ``snap``: the engine snapshot (fiducial ids, positions, plan, camera model,
    engine's trust verdict). ``px_scale``: display px per camera px when ``image`` is the frame
    already downscaled for display (camera-pixel positions are scaled; marks and text are sized
    for the image drawn on). Returns the BGR image (a copy unless ``in_place``)."""
    img = image if in_place else image.copy()
    h, w = img.shape[:2]
    pose = snap.pose
    cam = snap.camera
    ids = list(pose.fiducial_status.keys()) if pose is not None else []
    by_id = {f.id: f for f in snap.fiducials}
    T = None
    if estimate is not None and getattr(estimate, "T_cam_ct", None) is not None:
        T = np.asarray(estimate.T_cam_ct, float)
    elif pose is not None and pose.T_cam_ct is not None:
        T = np.asarray(pose.T_cam_ct, float)
    status = list(getattr(estimate, "status", []) or [])
    if estimate is not None and len(status) == len(ids):
        status_by_id = dict(zip(ids, status))
    else:
        status_by_id = dict(pose.fiducial_status) if pose is not None else {}
    # vision's PoseEstimate: arrays in fiducial order; the engine's PoseSample ("sim-points"):
    # dicts keyed by fiducial id and no image points
    img_pts = np.asarray(getattr(estimate, "image_points_px", np.zeros((0, 2))), float).reshape(-1, 2) * px_scale
    res_raw = getattr(estimate, "residuals_px", None)
    if isinstance(res_raw, dict):
        residuals = np.array([res_raw.get(i, np.nan) for i in ids], float)
    elif res_raw is None:
        residuals = np.array([(pose.residuals_px.get(i, np.nan) if pose is not None else np.nan) for i in ids], float)
    else:
        residuals = np.asarray(res_raw, float).ravel()
    scale = max(0.5, w / 1280.0)

    proj = {}
    if T is not None and cam.K is not None and ids:
        centres = np.array([by_id[i].centre_lps_mm for i in ids if i in by_id])
        known = [i for i in ids if i in by_id]
        if len(known):
            uv = project_points(centres, T, cam.K, cam.dist) * px_scale
            proj = dict(zip(known, uv))
        plan = snap.plan
        if plan.entry_lps_mm is not None and plan.target_lps_mm is not None:
            e, t = project_points(np.array([plan.entry_lps_mm, plan.target_lps_mm]), T, cam.K, cam.dist) * px_scale
            if _finite(e) and _finite(t):
                cv2.line(img, _ipt(e), _ipt(t), MAGENTA, max(1, int(2 * scale)), cv2.LINE_AA)
                cv2.drawMarker(img, _ipt(e), CYAN, cv2.MARKER_CROSS, int(24 * scale), max(1, int(2 * scale)))
                cv2.drawMarker(img, _ipt(t), MAGENTA, cv2.MARKER_TILTED_CROSS, int(20 * scale), max(1, int(2 * scale)))

    ring = int(14 * scale)
    for j, fid in enumerate(ids):
        st = status_by_id.get(fid, "unknown")
        p_img = img_pts[j] if j < len(img_pts) else None
        p_proj = proj.get(fid)
        if st in HIDDEN:
            if _finite(p_proj):
                cv2.circle(img, _ipt(p_proj), ring, RED, max(2, int(3 * scale)), cv2.LINE_AA)
                word = "MOVED" if st == "moved" else "HIDDEN"
                _text(img, f"{fid} {word}", (_ipt(p_proj)[0] + ring + 4, _ipt(p_proj)[1] + 6), RED, 0.6 * scale)
            continue
        if _finite(p_proj):
            cv2.circle(img, _ipt(p_proj), ring, CYAN, max(1, int(2 * scale)), cv2.LINE_AA)
        if _finite(p_img):
            cv2.circle(img, _ipt(p_img), max(3, int(4 * scale)), GREEN, -1, cv2.LINE_AA)
            label = str(fid)
            r = residuals[j] if j < len(residuals) else np.nan
            if np.isfinite(r):
                label += f"  {r:.2f} px"
            _text(img, label, (_ipt(p_img)[0] + ring + 4, _ipt(p_img)[1] - 6), WHITE, 0.55 * scale)

    # banner
    bh = int(40 * scale)
    trusted = pose is not None and pose.trusted
    valid = trusted and T is not None
    colour = (40, 120, 40) if valid else (30, 30, 190)
    cv2.rectangle(img, (0, 0), (w, bh), colour, -1)
    if valid:
        n_seen = sum(1 for s in status_by_id.values() if s == "seen")
        fre = f"{pose.fre_mm:.2f} mm" if pose.fre_mm is not None else "-"
        tre = f"{pose.predicted_tre_mm:.2f} mm" if pose.predicted_tre_mm is not None else "-"
        msg = f"POSE OK   FRE {fre}   predicted TRE {tre}   fiducials {n_seen}/{len(ids)}"
    elif pose is None:
        msg = "NO POSE YET: waiting for the first registration"
    else:
        msg = f"POSE NOT VALID: {pose.reason}"
        if pose.predicted_tre_mm is not None and "predicted error" not in pose.reason:
            msg += f"   (predicted TRE {pose.predicted_tre_mm:.2f} mm)"
    _text(img, msg[:110], (int(10 * scale), int(28 * scale)), WHITE, 0.75 * scale, max(1, int(2 * scale)))
    return img


def frame_code_strip(index: int, bits: int = 20, cell: int = 16) -> np.ndarray:
    """A black/white strip (cell x bits*cell, BGR) encoding ``index`` in binary, most significant
    bit first, robust to JPEG compression. Used by the benchmark to read frame numbers back from
    the browser's screen; ``read_frame_code`` decodes it."""
    strip = np.zeros((cell, bits * cell, 3), np.uint8)
    for b in range(bits):
        if (int(index) >> (bits - 1 - b)) & 1:
            strip[:, b * cell:(b + 1) * cell] = 255
    return strip


def read_frame_code(strip_bgr_or_grey: np.ndarray, bits: int = 20, cell: int = 16) -> int:
    g = strip_bgr_or_grey if strip_bgr_or_grey.ndim == 2 else strip_bgr_or_grey.mean(axis=2)
    v = 0
    for b in range(bits):
        v = (v << 1) | int(g[cell // 4: 3 * cell // 4, b * cell + cell // 4: b * cell + 3 * cell // 4].mean() > 127)
    return v
