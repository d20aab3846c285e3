"""Intrinsic camera calibration from chessboard or ChArUco images (OpenCV).

``calibrate_chessboard(images, pattern=(cols, rows), square_mm)``: ``pattern`` counts the
board's INNER corners (OpenCV's convention: a board of 10x7 squares has 9x6 inner corners).
``calibrate_charuco(images, squares=(cols, rows), square_mm, marker_mm, dictionary)``:
``squares`` counts the squares. Both return a :class:`CalibrationResult` with the
:class:`CameraModel`, the RMS reprojection error (px), per-view RMS errors and the images that
were skipped with the reason. Fewer than ``min_views`` usable views raises :class:`InputError`.

The distortion model is OpenCV's 5-coefficient one (k1, k2, p1, p2, k3); k3 is fixed at 0
when fewer than 10 views are available (it is poorly constrained and over-fits).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from monotracker.errors import InputError

from .camera_model import CameraModel


@dataclass
class CalibrationResult:
    camera: CameraModel
    rms_px: float
    per_view_rms_px: dict
    skipped: dict = field(default_factory=dict)   # image name -> why

    def summary(self) -> str:
        return (f"calibrated from {len(self.per_view_rms_px)} views (skipped {len(self.skipped)}): "
                f"RMS {self.rms_px:.3f} px, fx={self.camera.K[0, 0]:.1f} fy={self.camera.K[1, 1]:.1f} "
                f"cx={self.camera.K[0, 2]:.1f} cy={self.camera.K[1, 2]:.1f}")


def parse_pattern(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6); raises InputError on anything else."""
    try:
        a, b = text.lower().split("x")
        cols, rows = int(a), int(b)
    except ValueError:
        raise InputError(f"board size {text!r}: write it as COLSxROWS, e.g. 9x6") from None
    if cols < 2 or rows < 2:
        raise InputError(f"board size {text!r}: need at least 2x2")
    return cols, rows


def _load_images(images) -> list[tuple[str, np.ndarray]]:
    out = []
    for i, im in enumerate(images):
        if isinstance(im, (str, Path)):
            p = Path(im)
            if not p.is_file():
                raise InputError(f"calibration image not found: {p}")
            img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise InputError(f"cannot read calibration image {p.name} (corrupt or not an image)")
            out.append((p.name, img))
        else:
            img = np.asarray(im)
            out.append((f"image {i}", cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img))
    if not out:
        raise InputError("no calibration images given")
    sizes = {img.shape for _, img in out}
    if len(sizes) > 1:
        raise InputError(f"calibration images differ in size ({sorted(sizes)}): use one camera mode")
    return out


def _calibrate(obj, img, names, size, skipped, min_views) -> CalibrationResult:
    if len(obj) < min_views:
        raise InputError(f"only {len(obj)} usable calibration views (need {min_views}); skipped: "
                         + "; ".join(f"{k}: {v}" for k, v in list(skipped.items())[:5]))
    flags = 0 if len(obj) >= 10 else cv2.CALIB_FIX_K3
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, None, None, flags=flags)
    per_view = {}
    for n, o, p, r, t in zip(names, obj, img, rvecs, tvecs):
        proj, _ = cv2.projectPoints(o, r, t, K, dist)
        per_view[n] = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - p.reshape(-1, 2)) ** 2, 1))))
    return CalibrationResult(CameraModel(K, dist.reshape(-1), size), float(rms), per_view, skipped)


def chessboard_views(images, pattern: tuple[int, int], square_mm: float):
    """The chessboard's corners in each image (paths or arrays): ``(obj, img, names, skipped,
    (w, h))`` with ``obj`` a list of (n, 3) float32 board points (mm, z = 0), ``img`` the matching
    (n, 1, 2) float32 corners (px, sub-pixel), ``skipped`` image name -> why. Raises
    :class:`InputError` for a non-positive square or unreadable images."""
    if not (square_mm > 0):
        raise InputError(f"square size must be positive, got {square_mm} mm")
    cols, rows = pattern
    grid = np.zeros((cols * rows, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_mm
    obj, img, names, skipped = [], [], [], {}
    loaded = _load_images(images)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    for name, gray in loaded:
        found, corners = cv2.findChessboardCorners(gray, (cols, rows),
                                                   cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            skipped[name] = f"no {cols}x{rows} chessboard found"
            continue
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), crit)
        obj.append(grid)
        img.append(corners)
        names.append(name)
    h, w = loaded[0][1].shape
    return obj, img, names, skipped, (w, h)


def calibrate_chessboard(images, pattern: tuple[int, int], square_mm: float, min_views: int = 4) -> CalibrationResult:
    """Calibrate from chessboard images (paths or arrays); see the module docstring."""
    obj, img, names, skipped, size = chessboard_views(images, pattern, square_mm)
    return _calibrate(obj, img, names, size, skipped, min_views)


def calibrate_charuco(images, squares: tuple[int, int], square_mm: float, marker_mm: float,
                      dictionary: str = "DICT_5X5_100", min_views: int = 4) -> CalibrationResult:
    """Calibrate from ChArUco board images; ``squares`` = (cols, rows) of squares."""
    if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, "CharucoDetector"):
        raise InputError("this OpenCV build has no ChArUco support; use a chessboard")
    if not hasattr(cv2.aruco, dictionary):
        raise InputError(f"unknown ArUco dictionary {dictionary!r} (e.g. DICT_5X5_100, DICT_4X4_50)")
    if not (0 < marker_mm < square_mm):
        raise InputError(f"marker size {marker_mm} mm must be positive and smaller than the square {square_mm} mm")
    board = cv2.aruco.CharucoBoard(squares, square_mm, marker_mm,
                                   cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)))
    det = cv2.aruco.CharucoDetector(board)
    obj, img, names, skipped = [], [], [], {}
    loaded = _load_images(images)
    for name, gray in loaded:
        ch_corners, ch_ids, _, _ = det.detectBoard(gray)
        if ch_ids is None or len(ch_ids) < 6:
            skipped[name] = "fewer than 6 ChArUco corners found"
            continue
        o, p = board.matchImagePoints(ch_corners, ch_ids)
        obj.append(o.astype(np.float32))
        img.append(p.astype(np.float32))
        names.append(name)
    h, w = loaded[0][1].shape
    return _calibrate(obj, img, names, (w, h), skipped, min_views)


def render_chessboard(camera: CameraModel, T_cam_board: np.ndarray, pattern: tuple[int, int], square_mm: float,
                      supersample: int = 2, rays: np.ndarray | None = None) -> np.ndarray:
    """Synthetic grey image of a chessboard seen by ``camera`` (with its distortion), for tests
    and for checking the calibration: our own ray-plane renderer, independent of OpenCV's
    projection. The board lies in its z = 0 plane, inner corner (0, 0) at its origin, with a
    one-square white margin. ``rays`` may pass precomputed ``camera.pixel_rays(supersample)``."""
    cols, rows = pattern
    d = camera.pixel_rays(supersample) if rays is None else rays
    R, t = T_cam_board[:3, :3], T_cam_board[:3, 3]
    n = R[:, 2]                                  # board normal in camera frame
    s = (n @ t) / (d @ n)                        # ray parameter to the plane
    # board-frame x, y of the camera-frame point P = s d: (P - t) @ R per axis, without the
    # (h, w, 3) float64 temporaries (a 1280x720 board at supersample 2 took 0.23 s with them)
    u = (s * (d @ R[:, 0]) - t @ R[:, 0]) / square_mm
    v = (s * (d @ R[:, 1]) - t @ R[:, 1]) / square_mm
    inside = (u > -2) & (u < cols + 1) & (v > -2) & (v < rows + 1) & (s > 0)
    on_board = (u > -1) & (u < cols) & (v > -1) & (v < rows)
    black = ((np.floor(u) + np.floor(v)) % 2 == 0) & on_board
    img = np.where(inside, np.where(black, 30.0, 220.0), 110.0).astype(np.float32)
    h, w = camera.height, camera.width
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA).round().astype(np.uint8)


def render_board_texture(camera: CameraModel, T_cam_board: np.ndarray, texture: np.ndarray, mm_per_px: float,
                         supersample: int = 2, rays: np.ndarray | None = None) -> np.ndarray:
    """Synthetic grey image of a flat printed board (``texture``: grey uint8, its pixel (0, 0)
    corner at the board origin, x along columns, ``mm_per_px`` print scale) seen by ``camera``:
    ray-plane intersection, bilinear texture lookup, area downsampling. Used to test ChArUco."""
    d = camera.pixel_rays(supersample) if rays is None else rays
    R, t = T_cam_board[:3, :3], T_cam_board[:3, 3]
    n = R[:, 2]
    s = (n @ t) / (d @ n)
    B = (d * s[..., None] - t) @ R
    mx = (B[..., 0] / mm_per_px - 0.5).astype(np.float32)   # texture pixel centres at (i + 0.5) * mm_per_px
    my = (B[..., 1] / mm_per_px - 0.5).astype(np.float32)
    img = cv2.remap(texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=110)
    img = np.where(s > 0, img, 110).astype(np.uint8)
    return cv2.resize(img, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
