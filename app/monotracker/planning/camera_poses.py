"""Camera poses the planner tries, inside the :class:`~.problem.CameraSpace` (CT LPS mm).

A pose is a viewing direction from the cone (unit, head -> camera), a distance and the point
it aims at; the camera is rolled so the image's long side spans the widest spread of the
skin it looks at. Poses come as ``T_ct_cam`` (4x4, OpenCV camera frame -> CT mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monotracker.geometry import look_at

#: golden angle (rad) of the Fibonacci spiral that spreads directions evenly over the cone
_GOLDEN = np.pi * (3.0 - np.sqrt(5.0))


def cone_directions(axis: np.ndarray, half_angle_deg: float, count: int) -> np.ndarray:
    """(count, 3) unit directions spread evenly (Fibonacci spiral, equal area) over the cone
    of ``half_angle_deg`` around ``axis``; the axis itself first."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    if count <= 1 or half_angle_deg <= 0:
        return axis[None].copy()
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    c_min = np.cos(np.radians(half_angle_deg))
    k = np.arange(count)
    cos_t = 1.0 - (1.0 - c_min) * k / (count - 1)     # equal-area steps in cos(theta)
    sin_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None))
    phi = k * _GOLDEN
    d = cos_t[:, None] * axis + sin_t[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclass(frozen=True)
class CameraPose:
    """``T_ct_cam`` (4x4) of a camera at ``distance_mm`` from ``aim`` (LPS mm) along
    ``direction`` (unit, aim -> camera)."""

    T_ct_cam: np.ndarray
    direction: np.ndarray
    distance_mm: float
    aim: np.ndarray

    @property
    def eye(self) -> np.ndarray:
        return self.T_ct_cam[:3, 3]


def aim_point(direction: np.ndarray, skin: np.ndarray, normals: np.ndarray, fixed: np.ndarray | None = None,
              facing_deg: float = 60.0) -> np.ndarray:
    """The point a camera looking along ``-direction`` aims at: ``fixed`` when given, else the
    centroid of the skin points (n, 3) whose normals face it within ``facing_deg``."""
    if fixed is not None:
        return np.asarray(fixed, float)
    facing = normals @ np.asarray(direction, float) > np.cos(np.radians(facing_deg))
    pts = skin[facing] if np.any(facing) else skin
    return pts.mean(axis=0)


def camera_pose(direction: np.ndarray, distance_mm: float, aim: np.ndarray, spread: np.ndarray) -> CameraPose:
    """The :class:`CameraPose` at ``aim + distance * direction`` looking at ``aim``, rolled so
    that the image x axis (the long side) lies along the principal axis of ``spread`` (n, 3)
    points as seen from there (ties: towards the patient's left, +x LPS)."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    aim = np.asarray(aim, float)
    eye = aim + float(distance_mm) * d
    z = -d
    P = np.asarray(spread, float).reshape(-1, 3)
    p1 = None
    if len(P) >= 3:
        Q = P - P.mean(axis=0)
        Q = Q - np.outer(Q @ z, z)
        _, _, vt = np.linalg.svd(Q, full_matrices=False)
        p1 = vt[0] - (vt[0] @ z) * z
    if p1 is None or np.linalg.norm(p1) < 1e-6:
        p1 = np.cross(z, [0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
    p1 /= np.linalg.norm(p1)
    if p1 @ np.array([1.0, 0.3, 0.1]) < 0:
        p1 = -p1
    up = np.cross(z, p1)          # look_at's image x = z x (-up) = p1
    return CameraPose(look_at(eye, aim, up), d, float(distance_mm), aim)


def candidate_poses(space, head_centre: np.ndarray, skin: np.ndarray, normals: np.ndarray,
                    n_directions: int = 24, n_distances: int = 2) -> list[CameraPose]:
    """The poses the search tries: ``n_directions`` over the cone x ``n_distances`` from the
    near end of the range to its far end, each aimed per :func:`aim_point` and rolled per
    :func:`camera_pose` over the skin facing it; poses the space forbids (occupied side, the
    robot's reach) are left out."""
    lo, hi = space.distance_mm
    dists = [lo] if n_distances <= 1 or hi <= lo else list(np.linspace(lo, hi, n_distances))
    out = []
    for d in cone_directions(space.axis, space.half_angle_deg, n_directions):
        aim = aim_point(d, skin, normals, space.aim)
        facing = normals @ d > np.cos(np.radians(60.0))
        for dist in dists:
            pose = camera_pose(d, dist, aim, skin[facing])
            if space.where_not(pose.eye, head_centre) == "":
                out.append(pose)
    return out
