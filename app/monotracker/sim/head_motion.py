"""Simulated head motion for the digital twin: how the patient's head moves in the operating room.

A motion is a function ``t (s) -> D(t)``, a 4x4 rigid displacement (mm) applied in the ROOM
(robot base) frame about the head centre: ``T_base_ct(t) = D(t) @ T_base_ct0``. Magnitudes are
what a head-clamp-free, sedated patient does (our choice; the paper moves a phantom by hand):

* ``still``: no motion.
* ``drift``: slow creep, 1.5 mm/s along a fixed direction plus 0.3 deg/s rotation, reversing
  every 8 s (stays within ~12 mm / 2.4 deg).
* ``breathing``: 0.25 Hz (15 breaths/min) sinusoid, 2.5 mm amplitude mostly vertical, 0.6 deg
  nodding rotation.
* ``jumps``: still, then a sudden 8 mm / 3 deg step every 4 s (first at 2 s), alternating
  direction (a cough or a bump on the table); each step completes within 50 ms.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from monotracker.geometry import make_transform, rotation_about_axis

Motion = Callable[[float], np.ndarray]
NAMES = ("still", "drift", "breathing", "jumps")


def _about(centre: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rotation R about ``centre`` followed by translation ``t`` (all room frame, mm)."""
    c = np.asarray(centre, float)
    return make_transform(R, c - R @ c + np.asarray(t, float))


def _triangle(t: float, period: float) -> float:
    """Triangle wave in [-1, 1] of the given period, 0 at t = 0, rising first."""
    ph = (t / period) % 1.0
    return 4 * ph if ph < 0.25 else (2 - 4 * ph if ph < 0.75 else 4 * ph - 4)


def head_motion(name: str, centre_base_mm: np.ndarray, seed: int = 0) -> Motion:
    """The motion ``name`` (see module docstring) about the head centre (room/base frame, mm)."""
    if name not in NAMES:
        raise ValueError(f"unknown head motion {name!r}; use one of {', '.join(NAMES)}")
    rng = np.random.default_rng(seed)
    c = np.asarray(centre_base_mm, float)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)

    if name == "still":
        return lambda t: np.eye(4)

    if name == "drift":
        def drift(t: float) -> np.ndarray:
            s = 8.0 * _triangle(t, 32.0)  # seconds of drift at full speed, +-8 -> +-12 mm
            return _about(c, rotation_about_axis(axis, np.radians(0.3 * s)), 1.5 * s * u)
        return drift

    if name == "breathing":
        vert = np.array([0.0, 0.0, 1.0]) * 0.9 + 0.1 * u
        vert /= np.linalg.norm(vert)
        nod = np.array([1.0, 0.0, 0.0])

        def breathing(t: float) -> np.ndarray:
            s = np.sin(2 * np.pi * 0.25 * t)
            return _about(c, rotation_about_axis(nod, np.radians(0.6 * s)), 2.5 * s * vert)
        return breathing

    def jumps(t: float) -> np.ndarray:
        if t < 2.0:
            return np.eye(4)
        k = int((t - 2.0) // 4.0)  # jumps completed before this one
        frac = min(1.0, ((t - 2.0) - 4.0 * k) / 0.05)
        level = frac if k % 2 == 0 else 1.0 - frac  # 0 -> 1 -> 0 -> 1 ...
        return _about(c, rotation_about_axis(axis, np.radians(3.0 * level)), 8.0 * level * u)
    return jumps
