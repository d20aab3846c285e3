"""CT slice views for the web app: axial, coronal and sagittal planes through an LPS point.

The planes are aligned with the patient axes (LPS), not with the voxel grid, so an oblique
scan still shows true axial/coronal/sagittal anatomy: each pixel is an LPS point (``pixel_mm``
apart) sampled from the volume by trilinear interpolation (outside the scan = air).

Display conventions (radiological, as CT viewers show them):

* axial (z = const): image right = patient left (+x), image down = posterior (+y);
* coronal (y = const): image right = patient left (+x), image down = inferior (-z);
* sagittal (x = const): image right = posterior (+y), image down = inferior (-z).

Fiducials within ``near_mm`` of a plane are drawn as numbered circles (green confirmed/added,
yellow detected, red rejected), the layout planner's suggested ball positions (issue 31) as blue
circles labelled S1..Sn (:func:`draw_suggested`, shared with the navigation views); the planned path is drawn projected onto each plane (entry
cyan, target magenta), solid where it is within ``near_mm`` of the plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

PLANES = ("axial", "coronal", "sagittal")

_LETTERS = (("R", "L"), ("A", "P"), ("I", "S"))  # (negative, positive) per LPS axis


def direction_letters(d, min_component: float = 0.3) -> str:
    """Orientation letters of an LPS direction: one letter per axis whose share of the unit
    vector is at least ``min_component`` (cos 72 deg), strongest first; e.g. (1, 0, 0) -> "L",
    (0, -0.7, 0.7) -> "AS" or "SA"."""
    d = np.asarray(d, float)
    d = d / np.linalg.norm(d)
    order = np.argsort(-np.abs(d), kind="stable")
    out = [_LETTERS[i][int(d[i] > 0)] for i in order if abs(d[i]) >= min_component]
    return "".join(out) or _LETTERS[order[0]][int(d[order[0]] > 0)]


def position_text(plane: str, point_lps) -> str:
    """Where a slice cuts, as a reader says it: "sagittal R 6.2 mm" (x = -6.2 LPS is right),
    "axial S 12.0 mm", "coronal A 3.1 mm"."""
    n = _AXES[plane][3]
    v = float(np.asarray(point_lps, float)[n])
    return f"{plane} {_LETTERS[n][int(v > 0)]} {abs(v):.1f} mm"


def edge_letters(plane: str) -> dict:
    """Orientation letters at the image's edge midpoints ({"left", "right", "top", "bottom"}),
    from the plane's axes (:data:`_AXES`; radiological convention)."""
    col, row, sign, _ = _AXES[plane]
    right = np.zeros(3)
    right[col] = 1.0
    down = np.zeros(3)
    down[row] = float(sign)
    return {"right": direction_letters(right), "left": direction_letters(-right),
            "bottom": direction_letters(down), "top": direction_letters(-down)}

#: (image-column axis, image-row axis, row direction sign) in LPS index 0=x 1=y 2=z per plane.
_AXES = {"axial": (0, 1, +1, 2), "coronal": (0, 2, -1, 1), "sagittal": (1, 2, -1, 0)}

#: the layout planner's suggested balls, as in the 3D view (blue; ui/layout_panel.py draws them there)
SUGGESTED_BGR = (230, 90, 30)

STATUS_BGR = {
    "confirmed": (80, 220, 80),
    "added": (80, 220, 80),
    "detected": (0, 215, 255),
    "rejected": (60, 60, 255),
}


@dataclass(frozen=True)
class SliceGeometry:
    """Where a slice image lies: ``plane``, the LPS point it passes through, the LPS bounds
    (min, max) of the volume, and ``pixel_mm``. ``to_pixel(p)`` maps LPS points to (col, row)."""

    plane: str
    point_lps: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    pixel_mm: float

    def size(self) -> tuple[int, int]:
        """(width, height) px."""
        c, r, _, _ = _AXES[self.plane]
        w = int(np.ceil((self.hi[c] - self.lo[c]) / self.pixel_mm)) + 1
        h = int(np.ceil((self.hi[r] - self.lo[r]) / self.pixel_mm)) + 1
        return w, h

    def to_pixel(self, p_lps: np.ndarray) -> np.ndarray:
        """LPS points (n, 3) mm -> pixel (col, row) (n, 2) float."""
        p = np.atleast_2d(np.asarray(p_lps, float))
        c, r, sign, _ = _AXES[self.plane]
        col = (p[:, c] - self.lo[c]) / self.pixel_mm
        row = (p[:, r] - self.lo[r]) / self.pixel_mm if sign > 0 else (self.hi[r] - p[:, r]) / self.pixel_mm
        return np.column_stack([col, row])

    def to_lps(self, col: float, row: float) -> np.ndarray:
        """Pixel (col, row) -> the LPS point (mm) on this plane."""
        c, r, sign, n = _AXES[self.plane]
        p = np.array(self.point_lps, float).copy()
        p[c] = self.lo[c] + col * self.pixel_mm
        p[r] = self.lo[r] + row * self.pixel_mm if sign > 0 else self.hi[r] - row * self.pixel_mm
        return p

    def distance_to_plane(self, p_lps: np.ndarray) -> np.ndarray:
        n = _AXES[self.plane][3]
        return np.abs(np.atleast_2d(np.asarray(p_lps, float))[:, n] - self.point_lps[n])


def outlined_text(img, text: str, org, scale: float, colour, thick: int = 2, outline: int | None = None) -> None:
    """``text`` on ``img`` (BGR, in place) at ``org`` (px, baseline left) in ``colour``, ``thick``
    px strokes over a black outline ``outline`` px wide (default ``thick + 3``): readable on any
    grey level of a CT slice."""
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), thick + 3 if outline is None else outline,
                cv2.LINE_AA)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thick, cv2.LINE_AA)


def draw_suggested(img, centres_lps, radius_mm: float, px, depth_mm, pixel_mm: float, scale: float,
                   near_mm: float = 6.0) -> int:
    """Draw the suggested ball positions ``centres_lps`` ((n, 3) LPS mm, numbered 1..n in this order)
    within ``near_mm`` of the image's plane on ``img`` (BGR, in place) as blue circles
    ``radius_mm + 2`` mm wide (as the fiducials) with a filled centre dot and the label "S<k>"
    left of the circle (fiducial ids sit right of theirs, so a kept fiducial shows both).
    ``px(p)`` maps an LPS point to the image's (col, row) px, ``depth_mm(p)`` gives its signed or
    absolute distance to the plane (mm); ``pixel_mm`` mm per unscaled pixel, ``scale`` the image's
    upscale. Returns how many were drawn."""
    drawn = 0
    if centres_lps is None:
        return 0
    rad = max(4, int(round((float(radius_mm) + 2.0) / pixel_mm * scale)))
    for k, p in enumerate(np.asarray(centres_lps, float).reshape(-1, 3)):
        if abs(float(np.ravel(depth_mm(p))[0])) > near_mm:
            continue
        c = px(p)
        cv2.circle(img, c, rad, SUGGESTED_BGR, 2, cv2.LINE_AA)
        cv2.circle(img, c, 2, SUGGESTED_BGR, -1, cv2.LINE_AA)
        label = f"S{k + 1}"
        (tw, _), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 2)
        org = (c[0] - rad - 2 - tw, c[1] - rad)
        outlined_text(img, label, org, 0.6, SUGGESTED_BGR, outline=4)
        drawn += 1
    return drawn


#: the steps whose slice views show the suggested balls (the layout is planned there)
SUGGESTION_STEPS = ("plan",)


def suggested_balls(snap, step: str):
    """What the slice views of ``step`` ("ct" | "plan" | "robot") draw of the layout: (the suggested
    ball centres, (n, 3) LPS mm, numbered 1..n in this order, or None; their ball radius mm).
    None without a planned layout and outside :data:`SUGGESTION_STEPS` (at the Robot step the
    slices show the balls that are on the head, not advice)."""
    lay = getattr(snap, "layout", None)
    if step not in SUGGESTION_STEPS or lay is None or not lay.ready:
        return None, 4.0
    return np.asarray(lay.balls_lps_mm, float), float(lay.radius_mm or 4.0)


def volume_bounds_lps(volume) -> tuple[np.ndarray, np.ndarray]:
    """LPS bounding box (min, max) mm of the volume's voxel centres."""
    nz, ny, nx = volume.array.shape
    corners = np.array([[i, j, k] for i in (0, nx - 1) for j in (0, ny - 1) for k in (0, nz - 1)], float)
    lps = volume.index_to_lps(corners)
    return lps.min(axis=0), lps.max(axis=0)


def slice_geometry(volume, plane: str, point_lps, pixel_mm: float = 1.0) -> SliceGeometry:
    if plane not in PLANES:
        raise ValueError(f"plane must be one of {PLANES}")
    lo, hi = volume_bounds_lps(volume)
    p = np.clip(np.asarray(point_lps, float).reshape(3), lo, hi)
    return SliceGeometry(plane, p, lo, hi, float(pixel_mm))


def sample_slice(volume, geom: SliceGeometry) -> np.ndarray:
    """HU values (h, w) float32 of the plane (air, -1000 HU, outside the scan)."""
    w, h = geom.size()
    cols, rows = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    c, r, sign, n = _AXES[geom.plane]
    pts = np.empty((h * w, 3))
    pts[:, n] = geom.point_lps[n]
    pts[:, c] = geom.lo[c] + cols.ravel() * geom.pixel_mm
    pts[:, r] = (geom.lo[r] + rows.ravel() * geom.pixel_mm) if sign > 0 else (geom.hi[r] - rows.ravel() * geom.pixel_mm)
    ijk = volume.lps_to_index(pts)
    vals = map_coordinates(volume.array, [ijk[:, 2], ijk[:, 1], ijk[:, 0]], order=1, mode="constant", cval=-1000.0)
    return vals.reshape(h, w).astype(np.float32)


def window_hu(hu: np.ndarray, level: float = 300.0, width: float = 2000.0) -> np.ndarray:
    """HU -> uint8 grey with a window (defaults show skin, bone and the ceramic balls)."""
    g = (hu - (level - width / 2.0)) / width * 255.0
    return np.clip(g, 0, 255).astype(np.uint8)


def render_slice(volume, plane: str, point_lps, fiducials=(), entry=None, target=None, *,
                 pixel_mm: float = 1.0, near_mm: float = 6.0, scale: int = 2, suggested=None,
                 suggested_radius_mm: float = 4.0) -> tuple[np.ndarray, SliceGeometry]:
    """RGB uint8 image of one plane with fiducials and path drawn, and its geometry.

    ``fiducials``: objects with ``id``, ``centre_lps_mm``, ``radius_mm``, ``status`` (the
    engine's snapshot ``Fiducial``). ``entry``/``target``: LPS mm or None. ``scale``: the grey
    image is upscaled by this integer factor before drawing so labels stay legible.
    ``suggested``: (n, 3) LPS mm, the layout planner's suggested ball centres (S1..Sn) or None;
    ``suggested_radius_mm`` their ball radius.
    """
    geom = slice_geometry(volume, plane, point_lps, pixel_mm)
    grey = window_hu(sample_slice(volume, geom))
    img = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    if scale != 1:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_LINEAR)
    s = float(scale)

    def px(p):
        return tuple(int(round(v)) for v in (geom.to_pixel(p)[0] + 0.5) * s)

    for f in fiducials:
        d = float(geom.distance_to_plane(f.centre_lps_mm)[0])
        if d > near_mm:
            continue
        col = STATUS_BGR.get(f.status, (255, 255, 255))
        rad = max(4, int(round((f.radius_mm + 2.0) / geom.pixel_mm * s)))
        c = px(f.centre_lps_mm)
        cv2.circle(img, c, rad, col, 2, cv2.LINE_AA)
        cv2.putText(img, str(f.id), (c[0] + rad + 2, c[1] - rad), cv2.FONT_HERSHEY_SIMPLEX, 0.6, col, 2, cv2.LINE_AA)
    draw_suggested(img, suggested, suggested_radius_mm, px, geom.distance_to_plane, geom.pixel_mm, s, near_mm)
    if entry is not None and target is not None:
        e, t = px(entry), px(target)
        cv2.line(img, e, t, (255, 255, 0), 2, cv2.LINE_AA)
    if entry is not None:
        cv2.drawMarker(img, px(entry), (255, 255, 0), cv2.MARKER_CROSS, 18, 2)
    if target is not None:
        cv2.drawMarker(img, px(target), (255, 0, 255), cv2.MARKER_TILTED_CROSS, 18, 2)
    # crosshair of the slice point (thin, dim)
    cx, cy = px(geom.point_lps)
    cv2.line(img, (cx, 0), (cx, img.shape[0] - 1), (90, 90, 160), 1)
    cv2.line(img, (0, cy), (img.shape[1] - 1, cy), (90, 90, 160), 1)
    cv2.putText(img, position_text(plane, geom.point_lps), (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55,
                (230, 230, 230), 1, cv2.LINE_AA)
    h, w = img.shape[:2]
    for where, letter in edge_letters(plane).items():
        (tw, th), _ = cv2.getTextSize(letter, cv2.FONT_HERSHEY_SIMPLEX, 0.7, 2)
        org = {"left": (4, h // 2 + th // 2), "right": (w - tw - 4, h // 2 + th // 2),
               "top": (w // 2 - tw // 2, th + 26), "bottom": (w // 2 - tw // 2, h - 6)}[where]
        outlined_text(img, letter, org, 0.7, (80, 230, 255), outline=4)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB), geom
