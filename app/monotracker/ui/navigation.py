"""Navigation views of the CT: axial, coronal and sagittal slices through one LPS point (the
needle tip when the robot's tip is known in CT through a current trusted pose, else the planned
target) and two probe views of the planned path ("probe's eye": the plane perpendicular to the
path at the tip's depth; "along path": the plane that contains the path).

Pure functions (numpy, scipy, OpenCV); no viser here (``navigation_panel`` shows them).

Geometry: every view is a :class:`PlaneView`, a square image whose pixel (col, row) is the LPS
point ``centre + (col - c0) * pixel_mm * u + (row - c0) * pixel_mm * v`` (``u`` = image right,
``v`` = image down, unit LPS vectors; ``c0`` the centre pixel). HU values are sampled from the
volume there by trilinear interpolation (``scipy.ndimage.map_coordinates``; air outside).

Display convention (radiological, as CT viewers show it; our CT frame is LPS):

* axial: image right = patient Left (+x), image down = Posterior (+y): seen from the feet;
* coronal: image right = patient Left (+x), image down = Inferior (-z): seen from the front;
* sagittal: image right = Posterior (+y), image down = Inferior (-z): seen from the patient's left;
* probe's eye: looking along the needle (entry -> target into the screen); image down = the
  path-perpendicular part of Inferior, or of Posterior when the path runs within 30 deg of
  the head's S-I axis; image right = down x needle direction;
* along path: image down = along the needle (entry at the top, deeper further down); image
  right = the path-perpendicular part of patient Left (or of Posterior for a left-right path).

Every image carries orientation letters at its four edge midpoints (L/R/A/P/S/I; oblique
directions get two or three letters, strongest first), from the same ``u``/``v`` that place
the pixels, so the letters say where the patient is whatever the plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

from monotracker.engine.config import SessionConfig
from monotracker.ui.slices import STATUS_BGR, direction_letters, draw_suggested, outlined_text, window_hu

ORTHO = ("axial", "coronal", "sagittal")
PROBE = ("probe", "along")
VIEWS = ORTHO + PROBE
TITLES = {"axial": "axial", "coronal": "coronal", "sagittal": "sagittal", "probe": "probe's eye",
          "along": "along path"}

#: (image right, image down) unit LPS vectors of the three patient-axis planes (radiological).
ORTHO_AXES = {
    "axial": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    "coronal": ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0)),
    "sagittal": ((0.0, 1.0, 0.0), (0.0, 0.0, -1.0)),
}

#: window/level presets (width, level) HU
WL_PRESETS = {"bone": (2000.0, 400.0), "brain": (80.0, 40.0), "soft tissue": (400.0, 40.0)}

#: colours (BGR) of what is drawn on the images
ENTRY_BGR = (255, 255, 0)  # cyan
TARGET_BGR = (255, 0, 255)  # magenta
TIP_BGR = (0, 230, 255)  # yellow
PATH_BGR = (255, 220, 120)

@dataclass(frozen=True)
class PlaneView:
    """A square image of the CT on a plane (see the module doc). ``name`` one of :data:`VIEWS`;
    ``centre_lps`` LPS mm of the image centre; ``u``/``v`` unit LPS vectors of image right /
    image down; ``pixel_mm``; ``size`` px (width = height)."""

    name: str
    centre_lps: np.ndarray
    u: np.ndarray
    v: np.ndarray
    pixel_mm: float
    size: int

    @property
    def normal(self) -> np.ndarray:
        """Unit LPS vector into the screen (``u x v``)."""
        return np.cross(self.u, self.v)

    @property
    def c0(self) -> float:
        return (self.size - 1) / 2.0

    def to_lps(self, col, row) -> np.ndarray:
        """Pixel (col, row) (floats ok; arrays broadcast) -> LPS mm on the plane, (..., 3)."""
        col = np.asarray(col, float)[..., None]
        row = np.asarray(row, float)[..., None]
        return self.centre_lps + ((col - self.c0) * self.u + (row - self.c0) * self.v) * self.pixel_mm

    def to_pixel(self, p_lps) -> np.ndarray:
        """LPS points (n, 3) mm -> (n, 2) pixel (col, row) of their projection on the plane."""
        d = np.atleast_2d(np.asarray(p_lps, float)) - self.centre_lps
        return np.column_stack([d @ self.u / self.pixel_mm + self.c0, d @ self.v / self.pixel_mm + self.c0])

    def depth(self, p_lps) -> np.ndarray:
        """Signed distance (mm) of LPS points from the plane, + into the screen."""
        return (np.atleast_2d(np.asarray(p_lps, float)) - self.centre_lps) @ self.normal

    def letters(self) -> dict:
        """Orientation letters at the image edges: {"left", "right", "top", "bottom"} -> str."""
        return {"right": direction_letters(self.u), "left": direction_letters(-self.u),
                "bottom": direction_letters(self.v), "top": direction_letters(-self.v)}


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _perp(a, d) -> np.ndarray:
    """The part of ``a`` perpendicular to the unit ``d`` (not normalised)."""
    a = np.asarray(a, float)
    return a - (a @ d) * d


def probe_axes(direction) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) of the probe's-eye view for the path direction ``direction`` (entry -> target, LPS):
    u x v = direction (looking along the needle)."""
    d = _unit(direction)
    down = _perp((0.0, 0.0, -1.0), d)
    if np.linalg.norm(down) < 0.5:  # path within 30 deg of S-I: down = posterior
        down = _perp((0.0, 1.0, 0.0), d)
    v = _unit(down)
    return np.cross(v, d), v


def along_axes(direction) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) of the along-path view: v = the path direction, u = patient Left (else Posterior)
    made perpendicular to it."""
    d = _unit(direction)
    right = _perp((1.0, 0.0, 0.0), d)
    if np.linalg.norm(right) < 0.5:
        right = _perp((0.0, 1.0, 0.0), d)
    return _unit(right), d


def tip_in_ct(snap) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The needle tip and its axis (unit, tip -> where it advances) in CT LPS mm, from the robot's
    tool pose ``T_base_tip`` through ``T_base_ct`` (hand-eye @ latest trusted T_cam_ct), or
    (None, None) when either is unknown. Geometry only: whether that registration is still
    current is :func:`tip_blocked`'s question (:func:`nav_point` asks both)."""
    sc = snap.scene
    if sc.T_base_tip is None or sc.T_base_ct is None:
        return None, None
    T_ct_tip = np.linalg.inv(np.asarray(sc.T_base_ct, float)) @ np.asarray(sc.T_base_tip, float)
    return T_ct_tip[:3, 3].copy(), _unit(T_ct_tip[:3, 2])


def tip_blocked(snap, max_pose_age_s: float) -> str:
    """Why the needle tip in CT must not be shown as live ("" when it may): ``scene.T_base_ct``
    comes from the last *trusted* pose, which outlives occlusion, a frozen camera or a lost
    registration; the tip is only current while the newest pose is trusted, not held as stale
    and no older than ``max_pose_age_s`` (the session's limit, the same one the arm obeys)."""
    if getattr(snap.scene, "T_base_tip", None) is None:
        return "tip unknown: the robot reports no needle pose"
    pose = getattr(snap, "pose", None)
    if pose is None:
        return "tip unknown: no pose estimate yet"
    if getattr(pose, "stale", False):
        return f"tip unknown: pose stale ({pose.reason})"
    if not pose.trusted:
        return f"tip unknown: pose not trusted ({pose.reason})"
    if pose.age_s > max_pose_age_s:
        return f"tip unknown: pose stale ({1000 * pose.age_s:.0f} ms old, limit {1000 * max_pose_age_s:.0f} ms)"
    if snap.scene.T_base_ct is None:
        return "tip unknown: no hand-eye calibration or registration"
    return ""


@dataclass(frozen=True)
class NavPoint:
    """Where the views cut: ``point`` LPS mm; ``source`` "tip" | "target" | "picked" | "centre";
    ``tip``/``tip_axis`` the live needle in CT (or None); ``note`` one line on why a live view
    is not following the tip ("" when it is, or when it is not live)."""

    point: np.ndarray
    source: str
    tip: np.ndarray | None = None
    tip_axis: np.ndarray | None = None
    note: str = ""


def nav_point(snap, volume_centre, picked=None, live: bool = True, *,
              max_pose_age_s: float = SessionConfig.max_pose_age_s) -> NavPoint:
    """The slices' point: the live tip (when ``live``, known and current: :func:`tip_blocked`),
    else ``picked`` (an operator's "centre here"), else the planned target, else
    ``volume_centre``. A live view that cannot use the tip says why in ``note``."""
    note = tip_blocked(snap, max_pose_age_s) if live else ""
    tip, axis = tip_in_ct(snap) if live and not note else (None, None)
    if live and not note and tip is None:
        note = "tip unknown"
    if tip is not None:
        return NavPoint(tip, "tip", tip, axis)
    if picked is not None:
        return NavPoint(np.asarray(picked, float), "picked", note=note)
    t = snap.plan.target_lps_mm
    if t is not None:
        return NavPoint(np.asarray(t, float), "target", note=note)
    return NavPoint(np.asarray(volume_centre, float), "centre", note=note)


def plane_views(point, entry=None, target=None, *, fov_mm: float = 180.0, pixel_mm: float = 0.8) -> dict:
    """The views (name -> :class:`PlaneView`) through ``point`` (LPS mm). With a path (entry and
    target, LPS mm) also "probe" (perpendicular to the path where the path passes at the depth of
    ``point``, centred on the path) and "along" (the path's plane, centred on its middle, the whole
    path in view)."""
    p = np.asarray(point, float).reshape(3)
    size = int(round(fov_mm / pixel_mm)) | 1  # odd: the centre is a pixel centre
    out = {n: PlaneView(n, p, np.array(u, float), np.array(v, float), pixel_mm, size) for n, (u, v) in ORTHO_AXES.items()}
    if entry is None or target is None:
        return out
    e, t = np.asarray(entry, float), np.asarray(target, float)
    length = float(np.linalg.norm(t - e))
    if length < 1e-6:
        return out
    d = (t - e) / length
    on_path = e + float((p - e) @ d) * d
    u, v = probe_axes(d)
    out["probe"] = PlaneView("probe", on_path, u, v, pixel_mm, size)
    u, v = along_axes(d)
    fov_along = max(fov_mm, 1.4 * length)
    px_along = fov_along / size
    out["along"] = PlaneView("along", (e + t) / 2, u, v, px_along, size)
    return out


def sample_plane(volume, view: PlaneView) -> np.ndarray:
    """HU (size, size) float32 of the plane (-1000, air, outside the scan)."""
    rows, cols = np.mgrid[0:view.size, 0:view.size].astype(float)
    pts = view.to_lps(cols.ravel(), rows.ravel())
    ijk = volume.lps_to_index(pts)
    vals = map_coordinates(volume.array, [ijk[:, 2], ijk[:, 1], ijk[:, 0]], order=1, mode="constant", cval=-1000.0)
    return vals.reshape(view.size, view.size).astype(np.float32)


def _text(img, s, org, scale, colour=(235, 235, 235), thick=2) -> None:
    outlined_text(img, s, org, scale, colour, thick)


def draw_letters(img, letters: dict, scale: float = 0.9) -> None:
    """The orientation letters at the four edge midpoints of ``img`` (BGR, in place)."""
    h, w = img.shape[:2]
    for side, s in letters.items():
        (tw, th), _ = cv2.getTextSize(s, cv2.FONT_HERSHEY_SIMPLEX, scale, 2)
        org = {"left": (6, h // 2 + th // 2), "right": (w - tw - 6, h // 2 + th // 2),
               "top": (w // 2 - tw // 2, th + 8), "bottom": (w // 2 - tw // 2, h - 8)}[side]
        _text(img, s, org, scale, (120, 255, 255))


def render_view(hu: np.ndarray, view: PlaneView, *, width: float, level: float, entry=None, target=None,
                tip=None, tip_axis=None, fiducials=(), near_mm: float = 6.0, scale: int = 2,
                title: str | None = None, suggested=None, suggested_radius_mm: float = 4.0) -> np.ndarray:
    """RGB uint8 (scale*size)^2 image of one view: ``hu`` windowed (``width``/``level`` HU), the
    orientation letters, the path (entry cyan +, target magenta x, line between, projected on the
    plane), the tip (yellow ring, its axis 20 mm), fiducials within ``near_mm`` of the plane and
    the layout planner's suggested ball centres ``suggested`` ((n, 3) LPS mm or None; blue, S1..Sn;
    ball radius ``suggested_radius_mm``) within ``near_mm`` of it."""
    grey = window_hu(hu, level=level, width=width)
    img = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    if scale != 1:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_LINEAR)
    s = float(scale)

    def px(p):
        q = (view.to_pixel(p)[0] + 0.5) * s
        return int(round(q[0])), int(round(q[1]))

    for f in fiducials:
        if abs(float(view.depth(f.centre_lps_mm)[0])) > near_mm:
            continue
        col = STATUS_BGR.get(f.status, (255, 255, 255))
        rad = max(4, int(round((f.radius_mm + 2.0) / view.pixel_mm * s)))
        c = px(f.centre_lps_mm)
        cv2.circle(img, c, rad, col, 2, cv2.LINE_AA)
        _text(img, str(f.id), (c[0] + rad + 2, c[1] - rad), 0.6, col)
    draw_suggested(img, suggested, suggested_radius_mm, px, view.depth, view.pixel_mm, s, near_mm)
    if entry is not None and target is not None:
        cv2.line(img, px(entry), px(target), PATH_BGR, 2, cv2.LINE_AA)
        if view.name == "probe":  # where the path pierces this plane (its centre): a ring
            cv2.circle(img, px(view.centre_lps), 9, PATH_BGR, 2, cv2.LINE_AA)
    if entry is not None:
        cv2.drawMarker(img, px(entry), ENTRY_BGR, cv2.MARKER_CROSS, 22, 2)
    if target is not None:
        cv2.drawMarker(img, px(target), TARGET_BGR, cv2.MARKER_TILTED_CROSS, 22, 2)
    if tip is not None:
        c = px(tip)
        if tip_axis is not None:
            cv2.line(img, px(np.asarray(tip) - 20.0 * np.asarray(tip_axis)), c, TIP_BGR, 2, cv2.LINE_AA)
        cv2.circle(img, c, 7, TIP_BGR, 2, cv2.LINE_AA)
        cv2.circle(img, c, 2, TIP_BGR, -1, cv2.LINE_AA)
    draw_letters(img, view.letters())
    _text(img, title or TITLES.get(view.name, view.name), (8, img.shape[0] - 34), 0.6, thick=1)
    _text(img, f"W {width:.0f} L {level:.0f}", (8, img.shape[0] - 12), 0.5, thick=1)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
