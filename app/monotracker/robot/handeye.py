"""Eye-to-hand calibration: the fixed camera's pose in the robot base frame, ``T_base_cam``.

A calibration target (checkerboard) is fixed on the flange; for each of N robot poses
``T_base_tool0`` the camera observes the target pose ``T_cam_target`` (e.g. ``cv2.solvePnP``).
The unknowns ``T_base_cam`` and ``T_tool0_target`` satisfy
``T_base_tool0_i @ T_tool0_target = T_base_cam @ T_cam_target_i`` for all i. We use OpenCV's
``calibrateHandEye`` in its eye-to-hand form (robot poses inverted, so the solver's
"camera-to-gripper" output is camera-to-base), try the Tsai, Park, Horaud, Andreff and
Daniilidis solvers, and keep the one with the smallest residual.

Residuals: with both transforms estimated, each pose predicts the observed target pose; the
rotation (deg) and translation (mm) differences are reported per pose and as RMS/max.
Public units are millimetres (like the camera and CT side); the file is JSON.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import pathlib
import tempfile
from dataclasses import dataclass, field

import cv2
import numpy as np

from monotracker.errors import InputError
from monotracker.geometry import invert_transform, make_transform, rotation_angle_deg
from monotracker.robot.rigid import rigid_problem

METHODS = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}


@dataclass
class HandEyeResult:
    ok: bool
    reason: str
    T_base_cam_mm: np.ndarray = field(default_factory=lambda: np.full((4, 4), np.nan))
    T_tool0_target_mm: np.ndarray = field(default_factory=lambda: np.full((4, 4), np.nan))
    method: str = ""
    rotation_residuals_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))
    translation_residuals_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    n_poses: int = 0

    @property
    def rotation_rms_deg(self) -> float:
        r = self.rotation_residuals_deg
        return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")

    @property
    def translation_rms_mm(self) -> float:
        r = self.translation_residuals_mm
        return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")

    def to_json(self) -> dict:
        return {
            "kind": "monotracker.handeye.eye_to_hand",
            "units": "mm",
            "T_base_cam_mm": np.asarray(self.T_base_cam_mm).tolist(),
            "T_tool0_target_mm": np.asarray(self.T_tool0_target_mm).tolist(),
            "method": self.method,
            "n_poses": self.n_poses,
            "rotation_rms_deg": self.rotation_rms_deg,
            "rotation_max_deg": float(np.max(self.rotation_residuals_deg)) if self.n_poses else None,
            "translation_rms_mm": self.translation_rms_mm,
            "translation_max_mm": float(np.max(self.translation_residuals_mm)) if self.n_poses else None,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        }


def _mean_rotation(Rs: list[np.ndarray]) -> np.ndarray:
    U, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _residuals(T_bt, T_ct, T_bc):
    """Estimate T_tool0_target given T_base_cam; residuals of each pose (deg, mm)."""
    X = [invert_transform(a) @ T_bc @ b for a, b in zip(T_bt, T_ct)]
    T_tt = make_transform(_mean_rotation([x[:3, :3] for x in X]), np.mean([x[:3, 3] for x in X], axis=0))
    rot, tra = [], []
    for a, b in zip(T_bt, T_ct):
        pred = invert_transform(T_bc) @ a @ T_tt
        rot.append(rotation_angle_deg(pred[:3, :3], b[:3, :3]))
        tra.append(float(np.linalg.norm(pred[:3, 3] - b[:3, 3])))
    return T_tt, np.array(rot), np.array(tra)


def _check_poses(name, Ts) -> list[np.ndarray]:
    out = []
    for i, T in enumerate(Ts):
        why = rigid_problem(T, 1e-4, f"{name}[{i}]")
        if why:
            raise InputError(f"hand-eye: {why}")
        out.append(np.asarray(T, dtype=float))
    return out


def calibrate_eye_to_hand(T_base_tool0_mm, T_cam_target_mm, method: str = "best") -> HandEyeResult:
    """``T_base_cam`` from robot flange poses and observed target poses (both (N,4,4), mm).

    ``method``: one of ``tsai park horaud andreff daniilidis`` or ``best`` (all, smallest
    translation RMS wins). Needs >= 3 poses with rotations about non-parallel axes; returns
    ``ok=False`` with a reason otherwise. Raises :class:`InputError` for malformed input.
    """
    T_bt = _check_poses("T_base_tool0_mm", T_base_tool0_mm)
    T_ct = _check_poses("T_cam_target_mm", T_cam_target_mm)
    if len(T_bt) != len(T_ct):
        raise InputError(f"hand-eye: {len(T_bt)} robot poses but {len(T_ct)} target observations")
    n = len(T_bt)
    if n < 3:
        return HandEyeResult(False, f"hand-eye needs at least 3 poses, got {n}", n_poses=n)
    # Rotation diversity: relative rotations must span more than one axis.
    axes = []
    for i in range(1, n):
        Rrel = T_bt[0][:3, :3].T @ T_bt[i][:3, :3]
        rv, _ = cv2.Rodrigues(Rrel)
        if np.linalg.norm(rv) > np.radians(2.0):
            axes.append(rv.ravel() / np.linalg.norm(rv))
    if len(axes) < 2 or np.linalg.matrix_rank(np.array(axes), tol=0.1) < 2:
        return HandEyeResult(False, "hand-eye: robot poses must rotate the flange about at least two different axes (> 2 deg)", n_poses=n)
    if method != "best" and method not in METHODS:
        raise InputError(f"hand-eye: unknown method {method!r}; choose best or one of {', '.join(METHODS)}")
    inv_bt = [invert_transform(T) for T in T_bt]
    R_g = [T[:3, :3] for T in inv_bt]
    t_g = [T[:3, 3].reshape(3, 1) for T in inv_bt]
    R_t = [T[:3, :3] for T in T_ct]
    t_t = [T[:3, 3].reshape(3, 1) for T in T_ct]
    best: HandEyeResult | None = None
    for name in (METHODS if method == "best" else [method]):
        try:
            R, t = cv2.calibrateHandEye(R_g, t_g, R_t, t_t, method=METHODS[name])
        except cv2.error:
            continue
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            continue
        T_bc = make_transform(R, t.ravel())
        T_tt, rot, tra = _residuals(T_bt, T_ct, T_bc)
        res = HandEyeResult(True, "", T_bc, T_tt, name, rot, tra, n)
        if best is None or res.translation_rms_mm < best.translation_rms_mm:
            best = res
    if best is None:
        return HandEyeResult(False, "hand-eye: every OpenCV solver failed on these poses", n_poses=n)
    best.reason = (f"{best.method}: {n} poses, residual RMS {best.translation_rms_mm:.2f} mm / "
                   f"{best.rotation_rms_deg:.3f} deg")
    return best


def save_handeye(result: HandEyeResult, path) -> pathlib.Path:
    """Write the calibration atomically as JSON."""
    if not result.ok:
        raise InputError(f"hand-eye: refusing to save a failed calibration ({result.reason})")
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        json.dump(result.to_json(), fh, indent=2)
    os.replace(tmp, path)
    return path


def load_handeye(path) -> np.ndarray:
    """``T_base_cam_mm`` (4,4) from a file written by :func:`save_handeye`."""
    path = pathlib.Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        T = np.array(data["T_base_cam_mm"], dtype=float)
    except FileNotFoundError:
        raise InputError(f"hand-eye file not found: {path}") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"hand-eye file {path} is not a MonoTracker calibration ({type(exc).__name__})") from None
    _check_poses("T_base_cam_mm", [T])
    return T


# ---------------------------------------------------------------------------- simulation
@dataclass
class SimulatedCalibration:
    """Truth and data of a simulated calibration run (mm)."""

    T_base_cam_mm: np.ndarray
    T_tool0_target_mm: np.ndarray
    T_base_tool0_mm: list
    T_cam_target_mm: list
    q: list


def default_camera_pose_mm() -> np.ndarray:
    """A plausible OR camera: 1.0 m in front of and above the workspace, looking at it (mm)."""
    from monotracker.geometry import look_at

    return look_at(np.array([1200.0, -600.0, 1100.0]), np.array([500.0, 150.0, 300.0]), np.array([0.0, 0.0, 1.0]))


def simulate_calibration(n_poses: int = 15, pixel_noise: float = 0.2, seed: int = 0,
                         T_base_cam_mm: np.ndarray | None = None) -> SimulatedCalibration:
    """Move the simulated UR10 through ``n_poses`` random configurations around the ready pose;
    a 7x5 checkerboard (20 mm squares, on a bracket beside the flange, facing up) is projected
    into a 1280x720 camera (f = 1400 px) with Gaussian pixel noise and its pose recovered with
    ``cv2.solvePnP``, as the real procedure would. Poses where the board is not fully visible
    or faces away are skipped."""
    from monotracker.robot import kinematics as kin
    from monotracker.robot.lie import exp3

    rng = np.random.default_rng(seed)
    K = np.array([[1400.0, 0, 640.0], [0, 1400.0, 360.0], [0, 0, 1]])
    T_bc = default_camera_pose_mm() if T_base_cam_mm is None else np.asarray(T_base_cam_mm, float)
    # Board on a bracket beside the flange, facing back along -tool z (up when the tool points
    # down, towards an OR camera above the table), slightly turned.
    T_tt = make_transform(exp3(np.array([np.pi, 0.0, 0.0])) @ exp3(np.array([0.0, 0.0, 0.3])), [10.0, 90.0, 40.0])
    gx, gy = np.meshgrid(np.arange(7) * 20.0, np.arange(5) * 20.0)
    board = np.column_stack([gx.ravel() - 60.0, gy.ravel() - 40.0, np.zeros(gx.size)])
    T_bt, T_ct, qs = [], [], []
    tries = 0
    while len(T_bt) < n_poses and tries < 50 * n_poses:
        tries += 1
        q = kin.Q_READY + rng.uniform(-0.35, 0.35, 6) * np.array([1, 0.6, 0.6, 1.5, 1.5, 1.5])
        Tb = kin.fk(q)
        Tb[:3, 3] *= 1000.0
        T_true = invert_transform(T_bc) @ Tb @ T_tt
        pts_cam = board @ T_true[:3, :3].T + T_true[:3, 3]
        if np.any(pts_cam[:, 2] < 200):
            continue
        # board must face the camera (normal towards it) within 70 deg
        n_cam = T_true[:3, 2]
        if -n_cam @ (T_true[:3, 3] / np.linalg.norm(T_true[:3, 3])) < np.cos(np.radians(70)):
            continue
        uv = (pts_cam / pts_cam[:, 2:3]) @ K.T
        uv = uv[:, :2] + rng.normal(0, pixel_noise, (len(board), 2))
        if np.any(uv < 0) or np.any(uv[:, 0] > 1279) or np.any(uv[:, 1] > 719):
            continue
        ok, rvec, tvec = cv2.solvePnP(board, uv, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            continue
        R, _ = cv2.Rodrigues(rvec)
        T_bt.append(Tb)
        T_ct.append(make_transform(R, tvec.ravel()))
        qs.append(q)
    return SimulatedCalibration(T_bc, T_tt, T_bt, T_ct, qs)
