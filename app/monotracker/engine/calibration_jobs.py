"""Guided calibration jobs for the browser (engine side): camera intrinsics and hand-eye.

Both jobs collect views one at a time (a button in the UI calls ``capture(session)``, which takes the
newest camera frame, or ``add_view(image)`` directly), say after every view what was found and what
is still missing, and solve with the existing solvers (``vision.calibration``,
``robot.handeye``); nothing here re-implements them. Thread-safe (viser callbacks run on worker
threads); solving is done by the caller off the UI thread (a few hundred ms).

:class:`IntrinsicsJob` -- chessboard (``pattern`` = inner corners, cols x rows) or ChArUco
(``squares``, ``marker_mm``, ``dictionary``). Each view: the board is detected (else refused with
the reason), a view whose corners moved less than ``min_shift_frac`` of the image diagonal from an
accepted view is refused as a duplicate, and coverage is reported as the fraction of a ``grid``
(3 x 3) of image cells that board corners have reached plus the spread of board tilts (deg): a good
calibration needs the corners in every cell and tilts of 20-45 deg. ``solve()`` returns vision's
:class:`CalibrationResult` (RMS px, per-view RMS px) once ``min_views`` views are in;
``save(path)`` writes the camera model (OpenCV YAML or JSON; ``CameraModel.load`` reads it back).

:class:`HandEyeJob` -- eye-to-hand with a board on the flange: each view pairs the robot's flange
(or needle-tip: any frame rigid with the flange works) pose ``T_base_tool_mm`` with the board pose
the calibrated camera sees (``cv2.solvePnP`` on the detected corners); views whose flange rotation
differs by < 2 deg from an accepted one are refused (no information). ``solve()`` runs
``robot.handeye.calibrate_eye_to_hand`` (best of OpenCV's five solvers) and reports residuals per
view in mm and deg; ``save(path)`` writes the hand-eye JSON (``robot.handeye.load_handeye``), and
``Session.set_hand_eye(result.T_base_cam_mm)`` applies it.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import cv2
import numpy as np

from monotracker.errors import InputError


@dataclass
class ViewReport:
    """What happened to one captured view: ``accepted``, ``reason`` (one line), ``n_views`` accepted
    so far, ``coverage`` (0..1 of the image grid), ``cells`` (rows x cols bools), ``tilt_deg``
    spread of board tilts so far, ``ready`` enough views to solve."""

    accepted: bool
    reason: str
    n_views: int
    coverage: float = 0.0
    cells: list = field(default_factory=list)
    tilt_deg: float = 0.0
    ready: bool = False


def _gray(image) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise InputError(f"calibration image has dtype {img.dtype}, expected 8-bit")
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img


class _BoardDetector:
    """Board corners in an image: chessboard (``pattern`` inner corners) or ChArUco."""

    def __init__(self, pattern=None, square_mm: float = 25.0, squares=None, marker_mm=None,
                 dictionary: str = "DICT_5X5_100"):
        if square_mm <= 0:
            raise InputError(f"square size must be positive, got {square_mm} mm")
        self.square_mm = float(square_mm)
        if squares is not None:
            if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, "CharucoDetector"):
                raise InputError("this OpenCV build has no ChArUco support; use a chessboard")
            if not hasattr(cv2.aruco, dictionary):
                raise InputError(f"unknown ArUco dictionary {dictionary!r}")
            if marker_mm is None or not (0 < marker_mm < square_mm):
                raise InputError("ChArUco needs a marker size smaller than the square")
            self.kind = "charuco"
            self.board = cv2.aruco.CharucoBoard(tuple(squares), square_mm, marker_mm,
                                                cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)))
            self.det = cv2.aruco.CharucoDetector(self.board)
            self.spec = {"squares": list(squares), "square_mm": square_mm, "marker_mm": marker_mm,
                         "dictionary": dictionary}
        else:
            if pattern is None or len(pattern) != 2 or min(pattern) < 2:
                raise InputError("chessboard pattern must be (cols, rows) inner corners, at least 2x2")
            self.kind = "chessboard"
            self.pattern = (int(pattern[0]), int(pattern[1]))
            cols, rows = self.pattern
            self.grid = np.zeros((cols * rows, 3), np.float32)
            self.grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_mm
            self.spec = {"pattern": list(self.pattern), "square_mm": square_mm}

    def detect(self, gray: np.ndarray):
        """(object points (n, 3) mm, image points (n, 2) px) or a reason string."""
        if self.kind == "charuco":
            ch_corners, ch_ids, _, _ = self.det.detectBoard(gray)
            if ch_ids is None or len(ch_ids) < 6:
                return "fewer than 6 ChArUco corners found"
            o, p = self.board.matchImagePoints(ch_corners, ch_ids)
            return o.reshape(-1, 3).astype(np.float32), p.reshape(-1, 2).astype(np.float32)
        cols, rows = self.pattern
        found, corners = cv2.findChessboardCorners(gray, (cols, rows),
                                                   cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            return f"no {cols}x{rows} chessboard found (whole board in view, not too oblique, in focus?)"
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), crit)
        return self.grid.copy(), corners.reshape(-1, 2)


def _newest_image(session):
    fr = session.latest_frame()
    if fr is None:
        raise InputError("no camera frame yet: start the camera first")
    return fr[0]


class IntrinsicsJob:
    """Guided intrinsics capture (see the module docstring)."""

    def __init__(self, pattern=(9, 6), square_mm: float = 25.0, squares=None, marker_mm=None,
                 dictionary: str = "DICT_5X5_100", grid=(3, 3), min_views: int = 10, min_shift_frac: float = 0.05):
        self.board = _BoardDetector(pattern, square_mm, squares, marker_mm, dictionary)
        self.grid = (int(grid[0]), int(grid[1]))
        self.min_views = int(min_views)
        self.min_shift_frac = float(min_shift_frac)
        self._lock = threading.Lock()
        self.views: list[tuple[np.ndarray, np.ndarray]] = []  # (object mm, image px)
        self.image_size: tuple | None = None
        self.result = None

    def capture(self, session) -> ViewReport:
        """Take the session's newest camera frame as a view."""
        return self.add_view(_newest_image(session))

    def add_view(self, image) -> ViewReport:
        gray = _gray(image)
        size = (gray.shape[1], gray.shape[0])
        found = self.board.detect(gray)
        with self._lock:
            if self.image_size is not None and size != self.image_size:
                return self._report(False, f"image size {size} differs from the first view's {self.image_size}")
            if isinstance(found, str):
                return self._report(False, found)
            obj, img = found
            diag = float(np.hypot(*size))
            for _o2, i2 in self.views:
                if len(i2) == len(img) and np.mean(np.linalg.norm(i2 - img, axis=1)) < self.min_shift_frac * diag:
                    return self._report(False, "too close to a view already taken: move or tilt the board")
            self.image_size = size
            self.views.append((obj, img))
            self.result = None
            return self._report(True, f"view {len(self.views)} accepted ({len(img)} corners)")

    def _coverage(self):
        gx, gy = self.grid
        cells = np.zeros((gy, gx), bool)
        if self.image_size is None:
            return cells, 0.0
        w, h = self.image_size
        for _o, img in self.views:
            cx = np.clip((img[:, 0] / w * gx).astype(int), 0, gx - 1)
            cy = np.clip((img[:, 1] / h * gy).astype(int), 0, gy - 1)
            cells[cy, cx] = True
        return cells, self._tilt_spread()

    def _tilt_spread(self) -> float:
        """Spread (deg) of the board's apparent tilt: angle between views' homography normals,
        estimated from the corner layout (a cheap proxy without intrinsics: the aspect change of
        the board's bounding parallelogram)."""
        if len(self.views) < 2:
            return 0.0
        tilts = []
        for obj, img in self.views:
            H, _ = cv2.findHomography(obj[:, :2], img)
            if H is None:
                continue
            a, b = np.linalg.norm(H[:2, 0]), np.linalg.norm(H[:2, 1])
            tilts.append(np.degrees(np.arccos(np.clip(min(a, b) / max(a, b), 0, 1))))
        return float(max(tilts) - min(tilts)) if tilts else 0.0

    def _report(self, accepted: bool, reason: str) -> ViewReport:
        cells, tilt = self._coverage()
        n = len(self.views)
        ready = n >= self.min_views
        if accepted and not ready:
            reason += f"; {self.min_views - n} more needed"
        missing = int((~cells).sum())
        if accepted and missing:
            reason += f"; {missing} image cells not reached yet"
        return ViewReport(accepted, reason, n, float(cells.mean()) if cells.size else 0.0, cells.tolist(), tilt, ready)

    def status(self) -> ViewReport:
        with self._lock:
            return self._report(False, f"{len(self.views)} views")

    def remove_view(self, i: int) -> None:
        with self._lock:
            del self.views[int(i)]
            self.result = None

    def solve(self):
        """vision's CalibrationResult (camera model, RMS px, per-view RMS px)."""
        from monotracker.vision.calibration import _calibrate

        with self._lock:
            views = list(self.views)
            size = self.image_size
        if len(views) < self.min_views:
            raise InputError(f"{len(views)} views; at least {self.min_views} are needed")
        res = _calibrate([o for o, _ in views], [i.reshape(-1, 1, 2) for _, i in views],
                         [f"view {k + 1}" for k in range(len(views))], size, {}, self.min_views)
        with self._lock:
            self.result = res
        return res

    def save(self, path):
        if self.result is None:
            raise InputError("solve the calibration before saving it")
        return self.result.camera.save(path)


@dataclass
class HandEyeView:
    T_base_tool_mm: np.ndarray
    T_cam_board_mm: np.ndarray
    reprojection_rms_px: float


class HandEyeJob:
    """Guided eye-to-hand capture (see the module docstring). ``camera`` is the calibrated
    :class:`~monotracker.vision.camera_model.CameraModel` of the fixed camera."""

    def __init__(self, camera, pattern=(7, 5), square_mm: float = 20.0, squares=None, marker_mm=None,
                 dictionary: str = "DICT_5X5_100", min_views: int = 8, min_rotation_deg: float = 2.0):
        self.camera = camera
        self.board = _BoardDetector(pattern, square_mm, squares, marker_mm, dictionary)
        self.min_views = int(min_views)
        self.min_rotation_deg = float(min_rotation_deg)
        self._lock = threading.Lock()
        self.views: list[HandEyeView] = []
        self.result = None

    def capture(self, session) -> ViewReport:
        """The session's newest frame with the robot's current needle-tip pose (rigid with the flange)."""
        st = session.robot_status()
        if st is None or st.T_base_tip is None or not st.connected:
            raise InputError("no robot pose: connect the arm first")
        return self.add_view(np.asarray(st.T_base_tip, float), _newest_image(session))

    def add_view(self, T_base_tool_mm, image) -> ViewReport:
        from monotracker.geometry import make_transform, rotation_angle_deg

        T_bt = np.asarray(T_base_tool_mm, float)
        if T_bt.shape != (4, 4) or not np.all(np.isfinite(T_bt)):
            return self._report(False, "robot pose is not a finite 4x4 transform")
        found = self.board.detect(_gray(image))
        if isinstance(found, str):
            return self._report(False, found)
        obj, img = found
        ok, rvec, tvec = cv2.solvePnP(obj, img, self.camera.K, self.camera.dist, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            return self._report(False, "board pose could not be solved")
        proj, _ = cv2.projectPoints(obj, rvec, tvec, self.camera.K, self.camera.dist)
        rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
        R, _ = cv2.Rodrigues(rvec)
        with self._lock:
            for v in self.views:
                if rotation_angle_deg(v.T_base_tool_mm[:3, :3], T_bt[:3, :3]) < self.min_rotation_deg:
                    return self._report(False, f"flange rotated < {self.min_rotation_deg:g} deg from a view already "
                                        "taken: rotate the wrist further")
            self.views.append(HandEyeView(T_bt, make_transform(R, tvec.ravel()), rms))
            self.result = None
            return self._report(True, f"view {len(self.views)} accepted (board reprojection {rms:.2f} px)")

    def _report(self, accepted: bool, reason: str) -> ViewReport:
        n = len(self.views)
        if accepted and n < self.min_views:
            reason += f"; {self.min_views - n} more needed"
        return ViewReport(accepted, reason, n, ready=n >= self.min_views)

    def solve(self):
        """robot.handeye's HandEyeResult: T_base_cam (mm), residuals per view (mm, deg)."""
        from monotracker.robot.handeye import calibrate_eye_to_hand

        with self._lock:
            views = list(self.views)
        if len(views) < self.min_views:
            raise InputError(f"{len(views)} views; at least {self.min_views} are needed")
        res = calibrate_eye_to_hand([v.T_base_tool_mm for v in views], [v.T_cam_board_mm for v in views])
        with self._lock:
            self.result = res
        return res

    def save(self, path):
        from monotracker.robot.handeye import save_handeye

        if self.result is None:
            raise InputError("solve the hand-eye calibration before saving it")
        return save_handeye(self.result, path)
