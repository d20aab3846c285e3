"""Pinhole camera model with OpenCV distortion, and its files.

``CameraModel`` holds the intrinsics ``K`` (3x3, px), the OpenCV distortion coefficients
``dist`` (k1, k2, p1, p2[, k3, ...]) and the image size (width, height) in px. Points in the
camera frame are OpenCV's (x right, y down, z forward), in mm.

Files: OpenCV YAML as written by ``cv2.FileStorage`` (``camera_matrix``,
``distortion_coefficients``, ``image_width``, ``image_height``; the keys of OpenCV's own
calibration sample) and JSON with the same keys (``camera_matrix`` a 3x3 nested list,
``distortion_coefficients`` a flat list). Every bad file raises :class:`InputError` with one
line saying what is wrong.

Optional: the balls' colour (:class:`~monotracker.vision.ball_colour.BallColour`, learned from
a click) is saved with the calibration, as a JSON object ``ball_colour`` or YAML keys
``ball_colour_hue_lo`` / ``_hue_hi`` / ``_sat_min`` / ``_val_min``; files without it load with
``ball_colour = None`` (the detector's default green).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any
from pathlib import Path

import cv2
import numpy as np

from monotracker.errors import InputError
from monotracker.registration.projection import distort_normalised as registration_distort
from monotracker.registration.projection import normalised_to_pixels


_RAY_CACHE: dict = {}


@dataclass
class CameraModel:
    """Intrinsics ``K`` (3x3 px), distortion ``dist`` (OpenCV order) and ``image_size`` (w, h px).

    Args:
        K: (3, 3) float, px: ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, pixel centres at integer
            coordinates (OpenCV convention).
        dist: OpenCV distortion coefficients (k1, k2, p1, p2[, k3, ...]): 0, 4, 5, 8, 12 or 14
            values, acting on normalised coordinates.
        image_size: (width, height) px of the images this calibration is valid for.
        ball_colour: the balls' colour saved with this calibration
            (:class:`~monotracker.vision.ball_colour.BallColour`) or None (default green).

    Raises:
        InputError: one line (:func:`validate_intrinsics`): K not 3x3 or not finite,
            focal lengths <= 0 or more than 3x apart, principal point outside the image, a bad
            distortion length, a non-positive image size.
    """

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]
    #: the balls' colour saved with this calibration (BallColour) or None (default green)
    ball_colour: Any = None

    def __post_init__(self):
        self.K = np.asarray(self.K, dtype=float)
        self.dist = np.asarray(self.dist, dtype=float).reshape(-1)
        for side, key in zip(self.image_size, ("image width", "image height")):
            why = image_side_problem(side)
            if why:
                raise InputError(f"invalid camera model: {key} {why}")
        self.image_size = (int(float(self.image_size[0])), int(float(self.image_size[1])))
        problem = validate_intrinsics(self.K, self.dist, self.image_size)
        if problem:
            raise InputError(f"invalid camera model: {problem}")

    # ------------------------------------------------------------------ geometry
    @property
    def width(self) -> int:
        return self.image_size[0]

    @property
    def height(self) -> int:
        return self.image_size[1]

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """(n, 3) camera-frame points (mm, z > 0) -> (n, 2) distorted pixel coordinates."""
        p = np.asarray(points_cam, dtype=float).reshape(-1, 3)
        return distort_normalised(p[:, :2] / p[:, 2:3], self.K, self.dist)

    def undistort_points(self, pixels: np.ndarray) -> np.ndarray:
        """(n, 2) distorted pixels -> (n, 2) normalised undistorted coordinates (x/z, y/z)."""
        p = np.asarray(pixels, dtype=float).reshape(-1, 1, 2)
        if len(p) == 0:
            return np.zeros((0, 2))
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
        return cv2.undistortPointsIter(p, self.K, self.dist, None, None, crit).reshape(-1, 2)

    def pixel_rays(self, scale: float = 1.0) -> np.ndarray:
        """Unit ray directions (camera frame) through every pixel centre of the image rendered
        at ``scale`` (1.0 = full size): array (h, w, 3) float32, read-only. Pixel centres are at
        integer coordinates (OpenCV convention). Cached per intrinsics (undistorting a
        1280x720 grid takes ~1 s)."""
        key = (self.K.tobytes(), self.dist.tobytes(), self.image_size, float(scale))
        rays = _RAY_CACHE.get(key)
        if rays is None:
            if len(_RAY_CACHE) >= 8:
                _RAY_CACHE.clear()
            rays = _RAY_CACHE[key] = self._pixel_rays(scale)
            rays.flags.writeable = False
        return rays

    def _pixel_rays(self, scale: float) -> np.ndarray:
        w = int(round(self.width * scale))
        h = int(round(self.height * scale))
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        # pixel (u, v) at this scale covers full-size coordinate (u + 0.5) / scale - 0.5
        uf = (u + 0.5) / scale - 0.5
        vf = (v + 0.5) / scale - 0.5
        xn = self.undistort_points(np.column_stack([uf.ravel(), vf.ravel()]))
        d = np.column_stack([xn, np.ones(len(xn))])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d.reshape(h, w, 3).astype(np.float32)

    # ------------------------------------------------------------------ frame size
    def frame_size_problem(self, image_shape) -> str:
        """'' when an image of ``image_shape`` ((h, w[, c]) as numpy gives it) matches the
        calibration's ``image_size``, else one line saying what to do. Intrinsics are only valid
        at the resolution they were calibrated at: a camera that falls back to a lower
        resolution, or a cropped video, makes a plausible-looking but wrong pose (measured: a
        640x360 frame with a 1280x720 calibration gave FRE 0.67 mm and 630 mm at the target)."""
        h, w = int(image_shape[0]), int(image_shape[1])
        if (w, h) == self.image_size:
            return ""
        return (f"frame is {w}x{h} px but the camera calibration is for {self.width}x{self.height}: "
                "calibrate at this resolution, or if it is the same sensor binned or cropped say so "
                "(adapt the calibration with bin:N or crop:X,Y,W,H)")

    def scaled(self, factor: float) -> "CameraModel":
        """The same sensor read out binned / resized by ``factor`` (0.5 = 2x2 binning: a
        1280x720 calibration becomes 640x360). Pixel centres sit at integer coordinates, so
        ``u' = (u + 0.5) * factor - 0.5``; focal lengths scale by ``factor``; the distortion
        coefficients act on normalised coordinates and do not change."""
        f = float(factor)
        if not (np.isfinite(f) and f > 0):
            raise InputError(f"scale factor must be a positive number, not {factor!r}")
        S = np.array([[f, 0.0, 0.5 * f - 0.5], [0.0, f, 0.5 * f - 0.5], [0.0, 0.0, 1.0]])
        size = (int(round(self.width * f)), int(round(self.height * f)))
        if abs(size[0] - self.width * f) > 1e-6 or abs(size[1] - self.height * f) > 1e-6:
            raise InputError(f"scaling {self.width}x{self.height} by {f:g} does not give a whole number of pixels")
        K = S @ self.K
        return CameraModel(K, self.dist.copy(), size)

    def cropped(self, x0: int, y0: int, width: int, height: int) -> "CameraModel":
        """The same sensor read out as the window (x0, y0, width, height) px of the calibrated
        image: the principal point shifts by (-x0, -y0), nothing else changes."""
        x0, y0, width, height = (int(v) for v in (x0, y0, width, height))
        if x0 < 0 or y0 < 0 or width <= 0 or height <= 0 or x0 + width > self.width or y0 + height > self.height:
            raise InputError(f"crop {x0},{y0},{width},{height} does not lie inside the calibrated "
                             f"{self.width}x{self.height} image")
        K = self.K.copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        return CameraModel(K, self.dist.copy(), (width, height))

    def adapted(self, spec: str | None) -> "CameraModel":
        """Apply a user's explicit statement about the readout mode: ``""``/None (unchanged),
        ``"bin:N"`` (N x N binning, N an integer), ``"scale:F"`` or ``"crop:X,Y,W,H"`` (px of
        the calibrated image). Raises :class:`InputError` with one line on a bad spec."""
        if not spec:
            return self
        kind, _, arg = str(spec).partition(":")
        try:
            if kind == "bin":
                n = int(arg)
                if n < 1:
                    raise ValueError
                return self.scaled(1.0 / n)
            if kind == "scale":
                return self.scaled(float(arg))
            if kind == "crop":
                vals = [int(v) for v in arg.split(",")]
                if len(vals) != 4:
                    raise ValueError
                return self.cropped(*vals)
        except ValueError:
            pass
        raise InputError(f"camera adaptation {spec!r} not understood: use bin:N, scale:F or crop:X,Y,W,H")

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> Path:
        """Write OpenCV YAML (``.yml``/``.yaml``/``.xml``) or JSON (``.json``), chosen by the
        suffix of ``path``; returns ``path``. Raises :class:`InputError` for another suffix."""
        path = Path(path)
        if path.suffix.lower() == ".json":
            path.write_text(json.dumps(self.to_dict(), indent=2))
        elif path.suffix.lower() in (".yml", ".yaml", ".xml"):
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
            fs.write("image_width", self.width)
            fs.write("image_height", self.height)
            fs.write("camera_matrix", self.K)
            fs.write("distortion_coefficients", self.dist.reshape(1, -1))
            if self.ball_colour is not None:
                for k, v in self.ball_colour.to_dict().items():
                    fs.write(f"ball_colour_{k}", int(v))
            fs.release()
        else:
            raise InputError(f"camera file {path.name}: use a .yml/.yaml/.xml (OpenCV) or .json name")
        return path

    def to_dict(self) -> dict:
        d = {
            "image_width": self.width,
            "image_height": self.height,
            "camera_matrix": self.K.tolist(),
            "distortion_coefficients": self.dist.tolist(),
        }
        if self.ball_colour is not None:
            d["ball_colour"] = self.ball_colour.to_dict()
        return d

    @classmethod
    def load(cls, path: str | Path) -> "CameraModel":
        """Read OpenCV YAML/XML or JSON intrinsics (the keys of the module docstring).

        Args:
            path: a ``.json`` file, or an OpenCV ``FileStorage`` file (``.yml``/``.yaml``/``.xml``).

        Returns:
            the :class:`CameraModel`, with ``ball_colour`` when the file holds one.

        Raises:
            InputError: one line: missing file, unreadable or malformed content, missing keys,
                intrinsics that fail :func:`validate_intrinsics`.
        """
        path = Path(path)
        if not path.is_file():
            raise InputError(f"camera calibration file not found: {path}")
        if path.suffix.lower() == ".json":
            try:
                data = json.loads(path.read_text())
            except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
                raise InputError(f"camera file {path.name} is not valid JSON ({exc})") from None
            if not isinstance(data, dict):
                raise InputError(f"camera file {path.name}: expected a JSON object with camera_matrix")
            return cls._from_mapping(data, path.name)
        return cls._from_opencv(path)

    @classmethod
    def _from_opencv(cls, path: Path) -> "CameraModel":
        try:
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError):  # OpenCV's parser raises SystemError on binary garbage
            raise InputError(f"camera file {path.name} is not an OpenCV YAML/XML file") from None
        if not fs.isOpened():
            raise InputError(f"camera file {path.name} is not an OpenCV YAML/XML file")
        try:
            data = {}
            for key in ("camera_matrix", "distortion_coefficients"):
                node = fs.getNode(key)
                if node.empty():
                    continue
                try:
                    m = node.mat()
                except (cv2.error, SystemError):
                    m = None
                data[key] = None if m is None else m.tolist()
            for key in ("image_width", "image_height"):
                node = fs.getNode(key)
                if not node.empty():
                    data[key] = node.real()
            from .ball_colour import FIELDS

            colour = {k: fs.getNode(f"ball_colour_{k}").real() for k in FIELDS
                      if not fs.getNode(f"ball_colour_{k}").empty()}
            if colour:
                data["ball_colour"] = colour
        finally:
            fs.release()
        return cls._from_mapping(data, path.name)

    @classmethod
    def _from_mapping(cls, data: dict, name: str) -> "CameraModel":
        missing = [k for k in ("camera_matrix", "distortion_coefficients", "image_width", "image_height")
                   if data.get(k) is None]
        if missing:
            raise InputError(f"camera file {name} lacks {', '.join(missing)} (is it a calibration file?)")
        try:
            K = np.asarray(data["camera_matrix"], dtype=float)
            dist = np.asarray(data["distortion_coefficients"], dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise InputError(f"camera file {name}: camera_matrix/distortion_coefficients are not numbers") from None
        size = []
        for key in ("image_width", "image_height"):
            why = image_side_problem(data[key])
            if why:
                raise InputError(f"camera file {name}: {key} {why}")
            size.append(int(float(data[key])))
        size = tuple(size)
        problem = validate_intrinsics(K, dist, size)
        if problem:
            raise InputError(f"camera file {name}: {problem}")
        colour = None
        if data.get("ball_colour") is not None:
            from .ball_colour import BallColour

            colour = BallColour.from_dict(data["ball_colour"], f"camera file {name}: ball_colour")
        return cls(K, dist, size, colour)


#: largest image side (px) a calibration may claim (an 8K sensor is 7680 px wide); beyond it a
#: size is a typing or unit mistake, and the pixel grids built from it would not fit in memory
MAX_IMAGE_SIDE_PX = 20000
#: horizontal field of view (deg) a calibration may imply (fx and the image width, distortion
#: aside). A surgical camera 0.15-1.5 m from a head sees it with 5-120 deg; below 2 deg or above
#: 170 deg the focal length is in another unit (mm, or a value meant for another resolution)
FOV_LIMITS_DEG = (2.0, 170.0)
#: the lens distortion's local scale (singular values of its Jacobian on the normalised plane)
#: must stay within these bounds in the middle of the image: real lenses stay within ~0.3-1.3
#: (strong barrel squeezes the edges; tele lenses stretch a little); k1 = 50 stretches by ~6x
DISTORTION_SCALE_LIMITS = (0.15, 3.0)
#: undistorting then distorting an image point must give it back within this (px): otherwise the
#: distortion folds over there and a ball there has no single viewing ray
ROUND_TRIP_PX = 0.05
#: ... everywhere inside the ellipse of this share of the image's half width and half height.
#: Beyond it a fold is tolerated: a polynomial fitted to a wide lens often turns back near the
#: corners no board reached, and the detector claims no ball outline there (sphere_outline)
INVERTIBLE_SHARE = 0.8


def image_side_problem(value) -> str:
    """'' when ``value`` is a usable image side (a whole number of px, 1..MAX_IMAGE_SIDE_PX),
    else the rest of a one-line reason ("is infinite", ...)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return f"{value!r} is not a number"
    if not np.isfinite(v):
        return f"is {value!r}: must be a finite whole number of pixels"
    if v != int(v):
        return f"{v:g} is not a whole number of pixels"
    if v < 1:
        return f"{v:g} px is not positive"
    if v > MAX_IMAGE_SIDE_PX:
        return f"{v:g} px is outside 1-{MAX_IMAGE_SIDE_PX} px (a typing or unit mistake?)"
    return ""


def distortion_problem(K: np.ndarray, dist: np.ndarray, image_size: tuple[int, int]) -> str:
    """'' when the distortion coefficients describe a lens over the middle of the image, else one
    line. Points on the ellipse of ``INVERTIBLE_SHARE`` of the image's half width and height and
    on its middle lines are undistorted (OpenCV's iteration) and distorted again: a miss of more
    than ``ROUND_TRIP_PX`` means the model folds over or cannot be inverted there. At the same
    points the distortion's local scale must stay within ``DISTORTION_SCALE_LIMITS``."""
    dist = np.asarray(dist, float).reshape(-1)
    if not np.any(dist):
        return ""
    w, h = image_size
    cx0, cy0 = (w - 1) / 2, (h - 1) / 2
    a, b = INVERTIBLE_SHARE * (w - 1) / 2, INVERTIBLE_SHARE * (h - 1) / 2
    ang = np.linspace(0.0, 2 * np.pi, 48, endpoint=False)
    t = np.linspace(-1.0, 1.0, 17)
    pts = np.concatenate([np.column_stack([cx0 + a * np.cos(ang), cy0 + b * np.sin(ang)]),
                          np.column_stack([cx0 + a * t, np.full_like(t, cy0)]),
                          np.column_stack([np.full_like(t, cx0), cy0 + b * t])])
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    coeffs = ", ".join(f"{v:g}" for v in dist[:5])
    what = "check the order k1, k2, p1, p2, k3 and recalibrate"
    with np.errstate(all="ignore"):
        try:
            xn = cv2.undistortPointsIter(pts.reshape(-1, 1, 2), K, dist, None, None, crit).reshape(-1, 2)
            miss = np.linalg.norm(distort_normalised(xn, K, dist) - pts, axis=1)
        except cv2.error:
            xn, miss = np.full_like(pts, np.nan), np.full(len(pts), np.nan)
        if not np.all(np.isfinite(miss)) or miss.max() > ROUND_TRIP_PX:
            bad = int(np.argmax(np.where(np.isfinite(miss), miss, np.inf)))
            return (f"distortion_coefficients ({coeffs}) cannot be inverted in the middle of the {w}x{h} image "
                    f"(near pixel {pts[bad, 0]:.0f}, {pts[bad, 1]:.0f}): not a lens; {what}")
        e = 1e-6
        J = np.stack([(registration_distort(xn + [e, 0], dist) - registration_distort(xn - [e, 0], dist)) / (2 * e),
                      (registration_distort(xn + [0, e], dist) - registration_distort(xn - [0, e], dist)) / (2 * e)],
                     axis=2)                                    # (n, 2, 2): d distorted / d undistorted
        sv = np.linalg.svd(J, compute_uv=False)
    lo, hi = DISTORTION_SCALE_LIMITS
    if not np.all(np.isfinite(sv)) or sv.max() > hi or sv.min() < lo:
        k = int(np.argmax(sv.max(axis=1))) if sv.max() > hi else int(np.argmin(sv.min(axis=1)))
        s_bad = sv.max() if sv.max() > hi else sv.min()
        return (f"distortion_coefficients ({coeffs}) {'stretch' if s_bad > 1 else 'squeeze'} the image "
                f"{s_bad:.2g}x near pixel {pts[k, 0]:.0f}, {pts[k, 1]:.0f} (a lens stays within {lo:g}-{hi:g}x): "
                f"not a lens this model describes; {what}")
    return ""


def validate_intrinsics(K: np.ndarray, dist: np.ndarray, image_size: tuple[int, int]) -> str:
    """Return '' when the intrinsics are usable, else a one-line reason (what is wrong and
    what to do): see :class:`CameraModel`, :func:`image_side_problem`, ``FOV_LIMITS_DEG`` and
    :func:`distortion_problem`."""
    K = np.asarray(K, dtype=float)
    dist = np.asarray(dist, dtype=float).reshape(-1)
    if K.shape != (3, 3):
        return f"camera_matrix must be 3x3, got shape {K.shape}"
    if not np.all(np.isfinite(K)) or not np.all(np.isfinite(dist)):
        return "camera_matrix/distortion_coefficients contain NaN or infinity"
    for side, key in zip(image_size, ("image width", "image height")):
        why = image_side_problem(side)
        if why:
            return f"{key} {why}"
    w, h = (int(float(v)) for v in image_size)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if fx <= 0 or fy <= 0:
        return f"focal lengths must be positive (fx={fx:g}, fy={fy:g})"
    if abs(K[1, 0]) > 1e-9 or abs(K[2, 0]) > 1e-9 or abs(K[2, 1]) > 1e-9 or abs(K[2, 2] - 1) > 1e-9:
        return "camera_matrix must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]]"
    if not (0 <= cx <= w and 0 <= cy <= h):
        return f"principal point ({cx:g}, {cy:g}) lies outside the {w}x{h} image (wrong image size?)"
    if max(fx, fy) / min(fx, fy) > 3:
        return f"fx={fx:g} and fy={fy:g} differ more than 3x (wrong units or a swapped matrix?)"
    if len(dist) not in (0, 4, 5, 8, 12, 14):
        return f"distortion_coefficients must have 4, 5, 8, 12 or 14 values, got {len(dist)}"
    fov = float(np.degrees(2.0 * np.arctan2(w / 2.0, fx)))
    lo, hi = FOV_LIMITS_DEG
    if not (lo <= fov <= hi):
        return (f"fx={fx:g} px gives a {fov:.3g} deg field of view across {w} px (a camera that sees a head "
                f"has {lo:g}-{hi:g} deg): fx must be in pixels of this image size; recalibrate or fix the file")
    return distortion_problem(K, dist, (w, h))


def distort_normalised(xn: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(n, 2) normalised undistorted coordinates -> (n, 2) distorted pixels (OpenCV model; the
    registration's projection is the one implementation)."""
    xn = np.asarray(xn, dtype=float).reshape(-1, 2)
    return normalised_to_pixels(registration_distort(xn, dist), np.asarray(K, float))


def default_camera() -> CameraModel:
    """The simulated camera's intrinsics: 1280x720, f = 1100 px, mild barrel distortion."""
    K = np.array([[1100.0, 0.0, 641.3], [0.0, 1100.0, 358.2], [0.0, 0.0, 1.0]])
    dist = np.array([-0.12, 0.09, 0.0004, -0.0003, 0.0])
    return CameraModel(K, dist, (1280, 720))
