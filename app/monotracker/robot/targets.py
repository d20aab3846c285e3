"""Turning a planned puncture path into a needle-tip target pose, and checking it is reachable.

Public units: millimetres (frames as named by the caller: CT, camera or robot base). The
needle-tip frame has z along the path, pointing from the entry point towards the target (into
the head); the tip sits ``standoff_mm`` before the entry point on that line. A needle is
symmetric about z, so the roll (x axis) is free: pick it with ``x_hint`` or
:func:`align_roll` so the wrist does not turn for nothing.

Planned path -> robot target (mm): :func:`needle_target` maps the plan's entry and target (CT LPS)
through ``T_base_cam @ T_cam_ct`` into the base and makes the needle pose: tip on the entry (less
``standoff_mm``), +z from entry to target, roll closest to a reference orientation (the current
tip, or the previous target) so the tracker never spins the tool about its own axis for nothing;
without a reference, the roll whose x axis is closest to the base x axis. :func:`tip_and_axis_error`
measures an actual needle pose against the plan (tip to entry mm, axis angle deg).
"""

from __future__ import annotations

import numpy as np

from monotracker.errors import InputError
from monotracker.geometry import apply_transform, make_transform, rotation_about_axis
from monotracker.robot.kinematics import IKResult, NeedleTool, ik
from monotracker.robot.units import transform_mm_to_m


def needle_pose_from_path(entry_mm, target_mm, standoff_mm: float = 0.0, x_hint=None) -> np.ndarray:
    """``T_frame_tip`` (4,4, mm) for a path from ``entry_mm`` to ``target_mm`` (3,) in one frame."""
    e = np.asarray(entry_mm, dtype=float).reshape(-1)
    t = np.asarray(target_mm, dtype=float).reshape(-1)
    if e.shape != (3,) or t.shape != (3,) or not (np.all(np.isfinite(e)) and np.all(np.isfinite(t))):
        raise InputError("path: entry and target must be 3 finite coordinates (mm)")
    d = t - e
    n = np.linalg.norm(d)
    if n < 1.0:
        raise InputError(f"path: entry and target are {n:.2f} mm apart; need at least 1 mm")
    z = d / n
    hint = np.array([1.0, 0.0, 0.0]) if x_hint is None else np.asarray(x_hint, dtype=float)
    x = hint - (hint @ z) * z
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 1.0, 0.0]) - z[1] * z
    x /= np.linalg.norm(x)
    return make_transform(np.column_stack([x, np.cross(z, x), z]), e - standoff_mm * z)


def align_roll(T_target: np.ndarray, T_current: np.ndarray) -> np.ndarray:
    """``T_target`` turned about its own z so its x axis is as close as possible to
    ``T_current``'s (the needle axis and tip position are unchanged). Any units."""
    T = np.array(T_target, dtype=float)
    z = T[:3, 2]
    xc = T_current[:3, 0] - (T_current[:3, 0] @ z) * z
    if np.linalg.norm(xc) < 1e-9:
        return T
    xc /= np.linalg.norm(xc)
    ang = np.arctan2(np.cross(T[:3, 0], xc) @ z, T[:3, 0] @ xc)
    T[:3, :3] = rotation_about_axis(z, ang) @ T[:3, :3]
    return T


def reachable(T_base_tip_mm: np.ndarray, q0=None, tool: NeedleTool | None = None) -> IKResult:
    """IK for a needle-tip pose in the robot base frame (mm): ``ok`` says whether the UR10 can
    hold it; ``q`` is the joint configuration (rad) found from ``q0`` (default: ready pose)."""
    tool = tool or NeedleTool()
    return ik(transform_mm_to_m(T_base_tip_mm), q0, T_tool0_tool=tool.T_tool0_tip)


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
    :func:`needle_pose_from_path` (one definition of the needle frame)."""
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
