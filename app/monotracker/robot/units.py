"""The one millimetre <-> metre boundary of the robot package.

Everything inside ``monotracker.robot`` works in metres and radians (pinocchio, ur_rtde). The
public API that the engine calls (``Tracker.set_target``, ``Tracker.set_head_sphere``, the
snapshot's ``*_mm`` fields, ``fit_head_sphere``) takes and returns millimetres, like the CT,
camera and plan; those methods convert here and nowhere else.
"""

from __future__ import annotations

import numpy as np

MM_PER_M = 1000.0


def mm_to_m(x) -> np.ndarray | float:
    """Scalar or array in mm -> m."""
    if np.isscalar(x):
        return float(x) / MM_PER_M
    return np.asarray(x, dtype=float) / MM_PER_M


def m_to_mm(x) -> np.ndarray | float:
    """Scalar or array in m -> mm."""
    if np.isscalar(x):
        return float(x) * MM_PER_M
    return np.asarray(x, dtype=float) * MM_PER_M


def transform_mm_to_m(T_mm: np.ndarray) -> np.ndarray:
    """4x4 rigid transform with a translation in mm -> the same transform in m (copy)."""
    T = np.array(T_mm, dtype=float)
    T[:3, 3] /= MM_PER_M
    return T


def transform_m_to_mm(T_m: np.ndarray) -> np.ndarray:
    """4x4 rigid transform with a translation in m -> the same transform in mm (copy)."""
    T = np.array(T_m, dtype=float)
    T[:3, 3] *= MM_PER_M
    return T
