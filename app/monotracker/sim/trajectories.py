"""Head motion for the simulated camera: ``pose(t) -> T_world_ct`` (4x4, mm).

``world`` is the CT frame at rest (the head where the sample CT put it); a trajectory moves
the head rigidly, rotations about the phantom's head centre. All trajectories are
deterministic functions of time (seeded where random), so a frame index always renders the
same scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monotracker.geometry import make_transform, rotation_about_axis
from monotracker.sim.phantom import default_phantom

HEAD_CENTRE = default_phantom().centre_lps


def _about_centre(R: np.ndarray, t_mm: np.ndarray, centre: np.ndarray = HEAD_CENTRE) -> np.ndarray:
    """Rotate by R about ``centre`` then translate by ``t_mm`` (CT/world mm)."""
    return make_transform(R, centre - R @ centre + np.asarray(t_mm, float))


class Trajectory:
    """Base: ``pose(t_s) -> T_world_ct``."""

    def pose(self, t: float) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError


class Still(Trajectory):
    """The head does not move."""

    def pose(self, t):
        return np.eye(4)


@dataclass
class Drift(Trajectory):
    """Slow constant drift: ``velocity_mm_s`` (world mm/s) and a rotation of ``deg_per_s`` about
    ``axis`` through the head centre (a head sinking into its rest, ~0.2-1 mm/s)."""

    velocity_mm_s: tuple = (0.4, -0.2, 0.15)
    deg_per_s: float = 0.15
    axis: tuple = (0.3, 0.2, 1.0)

    def pose(self, t):
        R = rotation_about_axis(np.array(self.axis), np.radians(self.deg_per_s * t))
        return _about_centre(R, np.array(self.velocity_mm_s) * t)


@dataclass
class Breathing(Trajectory):
    """Breathing-like oscillation: ``amplitude_mm`` along ``direction`` with period ``period_s``,
    plus a nod of ``nod_deg`` about ``axis`` in phase (ventilated patient, head in a holder)."""

    amplitude_mm: float = 1.5
    period_s: float = 4.0
    direction: tuple = (0.0, 0.3, 1.0)
    nod_deg: float = 0.6
    axis: tuple = (1.0, 0.0, 0.0)

    def pose(self, t):
        s = np.sin(2 * np.pi * t / self.period_s)
        d = np.asarray(self.direction, float)
        d = d / np.linalg.norm(d)
        R = rotation_about_axis(np.array(self.axis), np.radians(self.nod_deg * s))
        return _about_centre(R, self.amplitude_mm * s * d)


@dataclass
class Jumps(Trajectory):
    """Sudden jumps: at each time in ``times_s`` the head moves by a random rigid step (up to
    ``max_mm`` and ``max_deg``) within ``duration_s`` (a bump against the head holder)."""

    times_s: tuple = (5.0, 15.0)
    max_mm: float = 6.0
    max_deg: float = 4.0
    duration_s: float = 0.1
    seed: int = 1
    _steps: list = field(default_factory=list, init=False, repr=False)

    def __post_init__(self):
        rng = np.random.default_rng(self.seed)
        for _ in self.times_s:
            t = rng.normal(size=3)
            t *= self.max_mm * rng.uniform(0.5, 1.0) / np.linalg.norm(t)
            ax = rng.normal(size=3)
            ang = np.radians(self.max_deg) * rng.uniform(0.3, 1.0) * rng.choice([-1, 1])
            self._steps.append((t, ax / np.linalg.norm(ax), ang))

    def pose(self, t):
        T = np.eye(4)
        for t0, (dt, ax, ang) in zip(self.times_s, self._steps):
            f = np.clip((t - t0) / self.duration_s, 0.0, 1.0)
            if f > 0:
                T = _about_centre(rotation_about_axis(ax, f * ang), f * dt) @ T
        return T


@dataclass
class Composite(Trajectory):
    """Product of trajectories (applied left to right: first one outermost)."""

    parts: tuple = ()

    def pose(self, t):
        T = np.eye(4)
        for p in self.parts:
            T = T @ p.pose(t)
        return T


TRAJECTORIES = ("still", "drift", "breathing", "jumps", "mixed")


def make_trajectory(name: str, seed: int = 1) -> Trajectory:
    """One of :data:`TRAJECTORIES`; ``mixed`` = drift + breathing + jumps at 12 s and 40 s."""
    if name == "still":
        return Still()
    if name == "drift":
        return Drift()
    if name == "breathing":
        return Breathing()
    if name == "jumps":
        return Jumps(seed=seed)
    if name == "mixed":
        return Composite((Jumps(times_s=(12.0, 40.0), seed=seed), Drift(), Breathing()))
    from monotracker.errors import InputError

    raise InputError(f"unknown trajectory {name!r}; use one of {', '.join(TRAJECTORIES)}")
