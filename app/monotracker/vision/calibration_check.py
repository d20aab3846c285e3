"""Is the camera calibration still right? What the constellation itself can say about the intrinsics.

A focal length that is wrong by ``e`` puts the head ``e * z`` too far (or near) along the viewing
rays (2 % at 450-530 mm: ~10 mm at the target) with residuals that do not change: a pinhole camera
cannot tell a longer focal length from a farther head. The balls' image size does not help either:
size and depth both scale with the focal length, so their ratio (the size check of
:mod:`.pose_checks`) is blind to it. What does see it is *perspective*: the balls lie at different
depths (~35 mm across the patch), and how their image spacing changes with depth depends on the
focal length alone. :func:`fit_intrinsics` fits the focal length scale and the principal point
shift, with each frame's pose free, to the matched balls of many frames (Gauss-Newton, poses
eliminated per frame by the Schur complement), and gives the standard errors that image noise
alone would give.

Honest limits (``benchmarks/calibration_checks.py`` measures them): image noise averages out over
frames, but the errors that stay with a ball (the CT's localisation of its centre, ~0.1 mm =
~0.25 px at 450 mm; a detector bias on that ball's background) do not, and with 5-9 balls on one
patch they leave a focal length uncertain by several per cent whatever the number of frames.
:func:`fit_intrinsics` is therefore a measuring tool, not an online alarm: with the per-ball error
floor (``IntrinsicsFit.std(static_px)``) included it could only call a focal length off by more
than ~25-45 % (a swapped lens), not a 2 % focus change. The start check against a known board
(:func:`check_with_board`; ``monotracker check-camera``, the calibration jobs) is the precise one;
the camera's autofocus is turned off at open (``frames.lock_focus``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from monotracker.registration.projection import distort_normalised, normalised_to_pixels, project_normalised


def _project(X_ct: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, K: np.ndarray, dist, radius_mm) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(rvec, float))
    Xc = X_ct @ R.T + tvec
    return normalised_to_pixels(distort_normalised(project_normalised(Xc, radius_mm), dist), K)


def _K_with(K: np.ndarray, c: np.ndarray) -> np.ndarray:
    """K with the focal lengths scaled by exp(c[0]) and the principal point shifted by c[1:] px."""
    K2 = np.array(K, float)
    K2[0, 0] *= np.exp(c[0])
    K2[1, 1] *= np.exp(c[0])
    K2[0, 1] *= np.exp(c[0])
    K2[0, 2] += c[1]
    K2[1, 2] += c[2]
    return K2


@dataclass
class IntrinsicsFit:
    """Result of :func:`fit_intrinsics`: ``f_scale`` (fitted focal length / calibrated, 1 = agree),
    ``dc_px`` (2,) principal point shift (px), ``cov`` (3, 3) covariance of (log f scale, dcx, dcy)
    from image noise alone (``sigma_px``), ``info1`` (3, 3) the information (per px^2) of one
    typical frame, ``rms_px`` residual RMS after the fit, ``frames`` and ``points`` used."""

    f_scale: float
    dc_px: np.ndarray
    cov: np.ndarray
    info1: np.ndarray
    sigma_px: float
    rms_px: float
    frames: int
    points: int

    def std(self, static_px: float = 0.0) -> np.ndarray:
        """Standard errors of (log f scale, dcx px, dcy px) with image noise and a per-ball error
        of ``static_px`` (px RMS per axis) that stays the same in every frame (it does not
        average out: it enters as one frame's worth of information)."""
        C = np.array(self.cov, float)
        if static_px > 0:
            C = C + static_px**2 * np.linalg.pinv(self.info1)
        return np.sqrt(np.maximum(np.diag(C), 0.0))


def fit_intrinsics(observations, fiducials_ct: np.ndarray, K: np.ndarray, dist, radius_mm: float | None,
                   iterations: int = 4) -> IntrinsicsFit | None:
    """Fit the focal length scale and principal point shift to pooled frames.

    Args:
        observations: iterable of ``(T_cam_ct (4, 4) mm, image_points (n, 2) px)``: a pose found
            with the calibration and the matched detection per CT fiducial (NaN rows where none).
        fiducials_ct: (n, 3) CT LPS mm.
        K, dist: the calibration under test (px; OpenCV distortion, kept fixed).
        radius_mm: ball radius (mm) for the ellipse-centre model, or None.

    Returns:
        :class:`IntrinsicsFit`, or None with fewer than 2 frames of >= 5 balls.
    """
    X = np.asarray(fiducials_ct, float)
    frames = []
    for T, pts in observations:
        pts = np.asarray(pts, float).reshape(-1, 2)
        ok = np.all(np.isfinite(pts), axis=1)
        if T is None or ok.sum() < 5:
            continue
        rv, _ = cv2.Rodrigues(np.asarray(T, float)[:3, :3])
        frames.append([rv.ravel().copy(), np.asarray(T, float)[:3, 3].copy(), X[ok], pts[ok]])
    if len(frames) < 2:
        return None
    c = np.zeros(3)
    for _ in range(iterations):
        A = np.zeros((3, 3))
        g = np.zeros(3)
        parts = []
        for fr in frames:
            rv, tv, Xk, uk = fr
            K2 = _K_with(K, c)
            r = (uk - _project(Xk, rv, tv, K2, dist, radius_mm)).ravel()
            p0 = np.r_[rv, tv]
            J = np.zeros((r.size, 9))
            for j in range(9):
                h = 1e-6 if j < 3 else (1e-4 if j < 6 else (1e-7 if j == 6 else 1e-4))
                dp, dc = np.zeros(6), np.zeros(3)
                if j < 6:
                    dp[j] = h
                else:
                    dc[j - 6] = h
                K3 = _K_with(K, c + dc)
                up = _project(Xk, (p0 + dp)[:3], (p0 + dp)[3:], K3, dist, radius_mm).ravel()
                dp[:] = 0
                dc[:] = 0
                if j < 6:
                    dp[j] = -h
                else:
                    dc[j - 6] = -h
                um = _project(Xk, (p0 + dp)[:3], (p0 + dp)[3:], _K_with(K, c + dc), dist, radius_mm).ravel()
                J[:, j] = (up - um) / (2 * h)
            Jp, Jc = J[:, :6], J[:, 6:]
            Hp = Jp.T @ Jp
            Hpi = np.linalg.pinv(Hp)
            S = Jc.T @ Jc - Jc.T @ Jp @ Hpi @ Jp.T @ Jc
            A += S
            g += Jc.T @ r - Jc.T @ Jp @ Hpi @ (Jp.T @ r)
            parts.append((Hpi, Jp, Jc, r, S))
        dc = np.linalg.lstsq(A, g, rcond=None)[0]
        for fr, (Hpi, Jp, Jc, r, _S) in zip(frames, parts):
            dp = Hpi @ (Jp.T @ (r - Jc @ dc))
            fr[0] = fr[0] + dp[:3]
            fr[1] = fr[1] + dp[3:]
        c = c + dc
        if np.all(np.abs(dc) < [1e-7, 1e-4, 1e-4]):
            break
    K2 = _K_with(K, c)
    res = np.concatenate([(fr[3] - _project(fr[2], fr[0], fr[1], K2, dist, radius_mm)).ravel() for fr in frames])
    n_pts = sum(len(fr[2]) for fr in frames)
    dof = max(res.size - 6 * len(frames) - 3, 1)
    sigma = float(np.sqrt(res @ res / dof))
    A_inv = np.linalg.pinv(A)
    return IntrinsicsFit(float(np.exp(c[0])), c[1:].copy(), sigma**2 * A_inv, A / len(frames), sigma,
                         float(np.sqrt(np.mean(res**2))), len(frames), n_pts)


# ---------------------------------------------------------------------------------- known board
#: defaults of :func:`check_with_board`: a focal length off by more than F_TOLERANCE (0.5 % puts a
#: target 500 mm away ~2.5 mm off) or a principal point off by more than C_TOLERANCE_PX (5 px:
#: ~2.6 mm) is a calibration that does not hold; Z_SIGMA standard errors make the verdict sure
F_TOLERANCE = 0.005
C_TOLERANCE_PX = 5.0
Z_SIGMA = 3.0


@dataclass
class BoardCheck:
    """Verdict of :func:`check_with_board`.

    ``verdict``: "agrees" (within the tolerances, surely), "disagrees" (off by more than a
    tolerance, surely) or "inconclusive" (the views cannot tell: add views). ``f_ratio`` the
    focal length the board shows / the calibration's; ``f_std`` its standard error (relative);
    ``dc_px`` (2,) principal point the board shows minus the calibration's (px; zeros when it
    was held fixed); ``dc_std`` (2,); ``distance_mm`` mean board distance; ``views``; ``rms_px``
    the corners' reprojection RMS; ``message`` one line for the operator."""

    verdict: str
    f_ratio: float
    f_std: float
    dc_px: np.ndarray
    dc_std: np.ndarray
    distance_mm: float
    views: int
    rms_px: float
    message: str

    @property
    def ok(self) -> bool:
        return self.verdict == "agrees"


def _dist_flags(n: int) -> int:
    """calibrateCamera flags that keep ``n`` distortion coefficients as given."""
    f = (cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K4 | cv2.CALIB_FIX_K5
         | cv2.CALIB_FIX_K6 | cv2.CALIB_FIX_TANGENT_DIST)
    if n >= 8:
        f |= cv2.CALIB_RATIONAL_MODEL
    if n >= 12:
        f |= cv2.CALIB_THIN_PRISM_MODEL | cv2.CALIB_FIX_S1_S2_S3_S4
    if n >= 14:
        f |= cv2.CALIB_TILTED_MODEL | cv2.CALIB_FIX_TAUX_TAUY
    return f


def check_with_board(camera, obj_points, img_points, f_tolerance: float = F_TOLERANCE,
                     c_tolerance_px: float = C_TOLERANCE_PX, z: float = Z_SIGMA) -> BoardCheck:
    """Check a calibration against views of a known board (the start check).

    The board's corners fix the focal length through perspective (a tilted board: its far side
    shrinks by how much depends on f alone) and, with three or more views, the principal point.
    The calibration's distortion is kept; focal length (fx/fy ratio kept) and principal point are
    fitted (``cv2.calibrateCameraExtended``, started from the calibration) with their standard
    errors, and compared with the calibration.

    Args:
        camera: the :class:`~.camera_model.CameraModel` under test.
        obj_points: list of (n, 3) board points (mm, board frame), one per view.
        img_points: list of (n, 2) or (n, 1, 2) detected corners (px), one per view.
        f_tolerance: relative focal length error that matters; c_tolerance_px: principal point (px).
        z: standard errors for a sure verdict.

    Returns:
        :class:`BoardCheck`. "disagrees" when the focal length or principal point is off by more
        than its tolerance and by more than ``z`` standard errors; "agrees" when both are surely
        within (estimate +- ``z`` standard errors inside the tolerance); else "inconclusive".
    """
    obj = [np.asarray(o, np.float32).reshape(-1, 3) for o in obj_points]
    img = [np.asarray(p, np.float32).reshape(-1, 1, 2) for p in img_points]
    if not obj or len(obj) != len(img):
        raise ValueError("check_with_board needs one set of image points per view")
    K0 = np.array(camera.K, float)
    d0 = np.array(camera.dist, float).reshape(-1)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO | _dist_flags(len(d0))
    free_c = len(obj) >= 3
    if not free_c:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    dist_in = d0 if len(d0) else np.zeros(5)
    rms, K, _d, rvecs, tvecs, std_in, _std_ex, _per_view = cv2.calibrateCameraExtended(
        obj, img, tuple(camera.image_size), K0.copy(), dist_in.copy(), flags=flags)
    std_in = np.asarray(std_in, float).ravel()
    f_ratio = float(K[0, 0] / K0[0, 0])
    # with the aspect ratio fixed OpenCV fits fy and derives fx: fx's deviation comes back 0, fy's is the one
    f_std = float(max(std_in[0], std_in[1]) / K[1, 1]) if std_in.size >= 2 else float("nan")
    dc = np.array([K[0, 2] - K0[0, 2], K[1, 2] - K0[1, 2]]) if free_c else np.zeros(2)
    dc_std = np.array([std_in[2], std_in[3]]) if free_c else np.zeros(2)
    dist_mm = float(np.mean([np.linalg.norm(t) for t in tvecs]))
    ef = f_ratio - 1.0
    off_f = abs(ef) > f_tolerance and abs(ef) > z * f_std
    off_c = free_c and bool(np.any((np.abs(dc) > c_tolerance_px) & (np.abs(dc) > z * dc_std)))
    sure_f = abs(ef) + z * f_std <= f_tolerance
    sure_c = (not free_c) or bool(np.all(np.abs(dc) + z * dc_std <= c_tolerance_px))
    at = dist_mm * abs(ef)
    if off_f or off_c:
        verdict = "disagrees"
        parts = []
        if off_f:
            parts.append(f"the focal length the board shows is {100 * abs(ef):.1f} % {'longer' if ef > 0 else 'shorter'} "
                         f"(+-{100 * f_std:.2f} %; ~{at:.0f} mm along the view at {dist_mm:.0f} mm)")
        if off_c:
            parts.append(f"the principal point is ({dc[0]:+.0f}, {dc[1]:+.0f}) px off (+-{max(dc_std):.1f} px)")
        message = ("camera calibration does not match the camera: " + " and ".join(parts)
                   + "; recalibrate (focus or zoom changed, or another lens?) and lock focus and zoom")
    elif sure_f and sure_c:
        verdict = "agrees"
        message = (f"camera calibration agrees with the board: focal length {100 * ef:+.2f} % (+-{100 * z * f_std:.2f} %)"
                   + (f", principal point ({dc[0]:+.1f}, {dc[1]:+.1f}) px" if free_c else
                      "; principal point not checked (3 or more views needed)"))
    else:
        verdict = "inconclusive"
        message = (f"calibration check inconclusive: the views fix the focal length only to +-{100 * z * f_std:.2f} %"
                   + (f" and the principal point to +-{z * max(dc_std):.1f} px" if free_c else "")
                   + f" (need +-{100 * f_tolerance:g} % / +-{c_tolerance_px:g} px): add views with the board tilted "
                     "20-45 deg, filling more of the image")
    return BoardCheck(verdict, f_ratio, f_std, dc, dc_std, dist_mm, len(obj), float(rms), message)
