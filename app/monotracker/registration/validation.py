"""Accuracy verification at validation fiducials (fiducials seen by the camera but NOT used in the fit).

FRE says how well the fit explains its own fiducials and does not predict target error; a
fiducial left out of the fit is an independent check (the paper's 4 validation fiducials). With one
camera, the measurable error at a validation fiducial is its distance to the **viewing ray** through
its detected image centre: the CT centre is mapped into the camera by the estimated ``T_cam_ct``
(mm), the detected ellipse centre is undistorted and corrected for the sphere-centre bias (the exact
model ``(a c, b c) / (c^2 - R^2)``, as the registration and the FRE use), and the perpendicular
distance of the mapped centre to that ray is the error (mm). This is the same point-to-ray distance
the FRE averages (``registration.report.fre_mm``), so FRE and validation error are directly
comparable. It is the error component across the line of sight; the component along it (depth) is
not observable from one image, so the value is a lower bound of the 3D error at that fiducial (for
a 30 deg viewing angle and errors that are not purely along the ray it is the larger part).

Each validation fiducial is matched to the detected blob nearest to where the estimated pose
projects it (exact sphere model), among blobs not used by the registration, within ``gate_px``; a
validation fiducial with no blob there is "not seen" and the verification fails (it cannot be
verified), as does any error above the limit. Units: mm, px; CT points LPS mm; camera OpenCV frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .projection import project_pixels, undistort_to_normalised
from .report import fre_mm

DEFAULT_GATE_PX = 25.0


@dataclass
class ValidationResult:
    """``errors_mm`` id -> point-to-ray error (mm) or None (not seen); ``image_points_px`` id ->
    matched detection (px) or None; ``max_mm`` the largest error (None if none measured);
    ``ok`` every validation fiducial seen and within ``limit_mm``; ``reason`` one line."""

    ok: bool
    reason: str
    errors_mm: dict = field(default_factory=dict)
    image_points_px: dict = field(default_factory=dict)
    max_mm: float | None = None
    limit_mm: float = 1.5

    def to_dict(self) -> dict:
        return {"ok": self.ok, "reason": self.reason, "limit_mm": self.limit_mm, "max_mm": self.max_mm,
                "errors_mm": {str(k): v for k, v in self.errors_mm.items()},
                "image_points_px": {str(k): v for k, v in self.image_points_px.items()}}


def match_detections(T_cam_ct: np.ndarray, X_ct: np.ndarray, detections_px: np.ndarray, K: np.ndarray,
                     dist: np.ndarray | None, radius_mm: float | None, gate_px: float = DEFAULT_GATE_PX,
                     used_px: np.ndarray | None = None) -> np.ndarray:
    """(m, 2) detection (px) matched to each CT point ``X_ct`` (m, 3), NaN where none within
    ``gate_px`` of its projection. Detections within 0.5 px of a ``used_px`` point (the
    registration's own) are not candidates. Greedy by distance, one detection per fiducial."""
    X = np.asarray(X_ct, float).reshape(-1, 3)
    det = np.asarray(detections_px, float).reshape(-1, 2)
    out = np.full((len(X), 2), np.nan)
    if len(X) == 0 or len(det) == 0:
        return out
    if used_px is not None and len(used_px):
        u = np.asarray(used_px, float).reshape(-1, 2)
        u = u[np.all(np.isfinite(u), axis=1)]
        if len(u):
            free = np.linalg.norm(det[:, None] - u[None], axis=2).min(axis=1) > 0.5
            det = det[free]
    if len(det) == 0:
        return out
    Xc = X @ T_cam_ct[:3, :3].T + T_cam_ct[:3, 3]
    front = Xc[:, 2] > (radius_mm or 0.0)
    proj = np.full((len(X), 2), np.nan)
    if front.any():
        proj[front] = project_pixels(Xc[front], K, dist, radius_mm)
    d = np.linalg.norm(proj[:, None] - det[None], axis=2)
    d[~np.isfinite(d)] = np.inf
    taken_f, taken_d = set(), set()
    for flat in np.argsort(d, axis=None):
        i, j = np.unravel_index(flat, d.shape)
        if d[i, j] > gate_px:
            break
        if i in taken_f or j in taken_d:
            continue
        out[i] = det[j]
        taken_f.add(i)
        taken_d.add(j)
    return out


def validate(T_cam_ct: np.ndarray, ids: list, X_ct: np.ndarray, detections_px: np.ndarray, K: np.ndarray,
             dist: np.ndarray | None, radius_mm: float | None, limit_mm: float,
             used_px: np.ndarray | None = None, gate_px: float = DEFAULT_GATE_PX) -> ValidationResult:
    """Verify ``T_cam_ct`` at the validation fiducials ``ids`` / ``X_ct`` (CT mm) against the
    frame's ``detections_px`` (all blobs, px); see the module docstring."""
    X = np.asarray(X_ct, float).reshape(-1, 3)
    if len(X) == 0:
        return ValidationResult(True, "no validation fiducials", limit_mm=limit_mm)
    matched = match_detections(T_cam_ct, X, detections_px, K, dist, radius_mm, gate_px, used_px)
    errors, points = {}, {}
    for k, fid in enumerate(ids):
        if not np.all(np.isfinite(matched[k])):
            errors[fid], points[fid] = None, None
            continue
        xn = undistort_to_normalised(matched[k][None], K, dist)
        errors[fid] = float(fre_mm(T_cam_ct, X[k][None], xn, radius_mm))  # one point: its ray distance
        points[fid] = [float(matched[k][0]), float(matched[k][1])]
    measured = [e for e in errors.values() if e is not None]
    mx = max(measured) if measured else None
    missing = [fid for fid, e in errors.items() if e is None]
    over = [fid for fid, e in errors.items() if e is not None and e > limit_mm]
    if missing:
        ok, reason = False, (f"validation fiducial{'s' if len(missing) > 1 else ''} {', '.join(map(str, missing))} "
                             f"not seen within {gate_px:g} px of where the registration puts "
                             f"{'them' if len(missing) > 1 else 'it'}: accuracy not verified")
    elif over:
        worst = max(over, key=lambda f: errors[f])
        ok, reason = False, (f"validation fiducial {worst} is {errors[worst]:.2f} mm off its viewing ray "
                             f"(limit {limit_mm:g} mm): registration not verified")
    else:
        ok, reason = True, f"{len(measured)} validation fiducials within {limit_mm:g} mm (max {mx:.2f} mm)"
    return ValidationResult(ok, reason, errors, points, mx, limit_mm)
