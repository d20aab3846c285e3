"""Rigid-transform helpers shared by every layer.

Transforms are 4x4 float64 arrays named ``T_to_from``: ``T_cam_ct @ p_ct = p_cam``.
Point arrays are ``(n, 3)`` float64. Units are whatever the caller's frames use (mm on the
CT/camera side, m on the robot side); these helpers are unit-agnostic.
"""

from __future__ import annotations

import numpy as np


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 transform from a 3x3 rotation ``R`` and a translation ``t`` (3,)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (``T_b_a`` -> ``T_a_b``)."""
    R = T[:3, :3]
    t = T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def apply_transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map ``(n, 3)`` (or ``(3,)``) points through ``T``; returns the same shape."""
    p = np.asarray(points, dtype=float)
    out = p.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
    return out.reshape(p.shape)


def rotation_about_axis(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """3x3 rotation by ``angle_rad`` about the unit direction of ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1 - np.cos(angle_rad)) * (K @ K)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``T_world_cam`` for an OpenCV camera (x right, y down, z forward) at ``eye`` looking at
    ``target``, with ``up`` (world frame) pointing roughly to the top of the image."""
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, -np.asarray(up, dtype=float))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: 'up' is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_transform(np.column_stack([x, y, z]), eye)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (deg) of the relative rotation ``R_a^T R_b``."""
    c = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def pose_jump(T_a: np.ndarray, T_b: np.ndarray, about_ct: np.ndarray) -> tuple[float, float]:
    """How far two estimates of ``T_cam_ct`` disagree: (mm at the CT point ``about_ct``, deg)."""
    pa = apply_transform(T_a, about_ct)
    pb = apply_transform(T_b, about_ct)
    Ra, Rb = np.asarray(T_a)[:3, :3], np.asarray(T_b)[:3, :3]
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.linalg.norm(pa - pb)), float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
