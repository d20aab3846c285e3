"""From a registration and the plan to the robot's needle target, and the errors that matter.

Frames and units: everything here is millimetres. ``T_base_cam`` (hand-eye) maps camera points to
the robot base; ``T_cam_ct`` (registration) maps CT LPS points to the camera; the plan's ``entry``
and ``target`` are CT LPS points.

Needle pose convention (shared with ``monotracker.robot``): the needle frame's origin is the needle
tip and its +z axis points along the needle, from the tip towards where it would advance. The
target pose puts the tip on the planned entry and +z along entry -> target. The roll about the
needle axis is free for the task; we choose it to be the roll closest to a reference orientation
(the current tip pose, or the previous target) so the tracker never spins the tool about its own
axis for nothing. Without a reference we pick the roll whose x axis is closest to the base x axis
(a deterministic choice).

``standoff_mm`` (default 0, as the issue states: tip at the entry) backs the tip off along the
path, e.g. to hold the needle a few mm above the skin.
"""

from __future__ import annotations

import numpy as np

from monotracker.geometry import apply_transform


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    if n < 1e-12:
        raise ValueError("zero-length direction")
    return np.asarray(v, float) / n


def needle_target(T_base_cam: np.ndarray, T_cam_ct: np.ndarray, entry_ct: np.ndarray, target_ct: np.ndarray,
                  reference_R: np.ndarray | None = None, standoff_mm: float = 0.0) -> np.ndarray:
    """``T_base_needle`` (4x4, mm): tip at the entry (minus ``standoff_mm`` along the path), +z from
    entry to target, roll closest to ``reference_R`` (3x3 rotation in base, e.g. the current tip).

    The path is mapped into the base frame (``T_base_cam @ T_cam_ct``) and turned into a pose by
    the robot package's ``needle_pose_from_path`` (one definition of the needle frame)."""
    from monotracker.robot.targets import needle_pose_from_path

    T_base_ct = np.asarray(T_base_cam, float) @ np.asarray(T_cam_ct, float)
    e = apply_transform(T_base_ct, np.asarray(entry_ct, float))
    g = apply_transform(T_base_ct, np.asarray(target_ct, float))
    x_hint = None if reference_R is None else np.asarray(reference_R, float)[:, 0]
    return needle_pose_from_path(e, g, standoff_mm=standoff_mm, x_hint=x_hint)


def tip_and_axis_error(T_base_tip: np.ndarray, T_base_ct: np.ndarray, entry_ct: np.ndarray,
                       target_ct: np.ndarray) -> tuple[float, float]:
    """(tip error mm, axis angle error deg) of an actual needle pose against the plan placed by
    ``T_base_ct`` (use the simulator's TRUE head pose for accuracy numbers).

    Tip error: distance from the needle tip to the planned entry. Axis error: angle between the
    needle's +z and the planned direction entry -> target."""
    e = apply_transform(T_base_ct, np.asarray(entry_ct, float))
    g = apply_transform(T_base_ct, np.asarray(target_ct, float))
    tip = np.asarray(T_base_tip, float)[:3, 3]
    z = np.asarray(T_base_tip, float)[:3, 2]
    d = _unit(g - e)
    ang = float(np.degrees(np.arccos(np.clip(float(z @ d) / float(np.linalg.norm(z)), -1.0, 1.0))))
    return float(np.linalg.norm(tip - e)), ang


def pose_jump(T_a: np.ndarray, T_b: np.ndarray, about_ct: np.ndarray) -> tuple[float, float]:
    """How far two estimates of ``T_cam_ct`` disagree: (mm at the CT point ``about_ct``, deg)."""
    pa = apply_transform(T_a, about_ct)
    pb = apply_transform(T_b, about_ct)
    Ra, Rb = np.asarray(T_a)[:3, :3], np.asarray(T_b)[:3, :3]
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.linalg.norm(pa - pb)), float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
