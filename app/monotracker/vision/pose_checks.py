"""Checks of a registered pose against physics and geometry, before it may be trusted.

The registration proves that a pose explains the image; these checks ask whether that pose can
be the real one (units: mm, px; camera frame OpenCV's):

* :func:`physical_problem` -- the camera-to-head distance lies in a plausible range (the
  fiducial centroid between ``min_distance_mm`` and ``max_distance_mm``), every CT fiducial
  (matched or not) lies in front of the camera, and the matched balls' image size agrees with
  their distance (minor semi-axis vs ``f R / z``, within ``size_ratio``). Note what it cannot
  do: a pinhole camera cannot tell a twice-as-large focal length from a twice-as-near head, so
  a wrong calibration at the right resolution passes the size test; a wrong resolution is
  caught by :meth:`CameraModel.frame_size_problem` first.
* :func:`weak_geometry` -- too few matched balls, or matched balls nearly collinear or
  coplanar (a pose from such a layout is poorly determined even when its residuals are small).

Each returns '' when fine, else one line naming the problem.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PhysicalLimits:
    """Plausible set-up (mm): camera to fiducial centroid; ratio of observed to expected ball
    image size (px/px)."""

    min_distance_mm: float = 150.0
    max_distance_mm: float = 1500.0
    size_ratio: tuple = (0.6, 1.6)


def physical_problem(T_cam_ct: np.ndarray, fiducials_ct: np.ndarray, radius_mm: float, focal_px: float,
                     matched: list | None = None, minor_axes_px: np.ndarray | None = None,
                     limits: PhysicalLimits | None = None) -> str:
    """'' or why the pose cannot be physical. ``matched`` fiducial indices whose detected
    ellipses have minor semi-axes ``minor_axes_px`` (same order)."""
    lim = limits or PhysicalLimits()
    T = np.asarray(T_cam_ct, float)
    Xc = np.asarray(fiducials_ct, float) @ T[:3, :3].T + T[:3, 3]
    d = float(np.linalg.norm(Xc.mean(axis=0)))
    if not (lim.min_distance_mm <= d <= lim.max_distance_mm):
        return (f"implausible pose: head {d:.0f} mm from the camera (expected {lim.min_distance_mm:.0f}-"
                f"{lim.max_distance_mm:.0f} mm); check the camera calibration")
    behind = np.flatnonzero(Xc[:, 2] <= radius_mm)
    if len(behind):
        return f"implausible pose: fiducial{'s' if len(behind) > 1 else ''} {', '.join(map(str, behind))} behind the camera"
    if matched is not None and minor_axes_px is not None and len(matched):
        b = np.asarray(minor_axes_px, float)
        z = Xc[np.asarray(matched, int), 2]
        expected = focal_px * radius_mm / np.sqrt(np.maximum(z**2 - radius_mm**2, 1e-9))
        ok = np.isfinite(b) & (b > 0)
        if ok.sum() >= 3:
            ratio = float(np.median(b[ok] / expected[ok]))
            lo, hi = lim.size_ratio
            if not (lo <= ratio <= hi):
                return (f"implausible pose: balls look {ratio:.2f}x the size their distance implies "
                        "(wrong calibration or not the fiducials)")
    return ""


def weak_geometry(fiducials_ct: np.ndarray, matched: list, min_fiducials: int = 4,
                  collinear_ratio: float = 0.1, coplanar_ratio: float = 0.03) -> str:
    """'' or why the matched layout cannot determine the pose well: fewer than
    ``min_fiducials``, or the matched balls' principal spreads (singular values s0 >= s1 >= s2
    of the centred CT points) with s1 / s0 < ``collinear_ratio`` or s2 / s0 < ``coplanar_ratio``."""
    matched = list(matched)
    if len(matched) < min_fiducials:
        return f"weak geometry: only {len(matched)} fiducials matched (need {min_fiducials})"
    P = np.asarray(fiducials_ct, float)[matched]
    s = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    ids = ", ".join(map(str, matched))
    if s[1] < collinear_ratio * s[0]:
        return f"weak geometry: matched fiducials {ids} are nearly collinear"
    if len(s) > 2 and s[2] < coplanar_ratio * s[0]:
        return f"weak geometry: matched fiducials {ids} are nearly coplanar"
    return ""
