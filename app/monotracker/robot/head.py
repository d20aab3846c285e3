"""The patient's head as the robot sees it: a sphere fitted to the fiducials by RANSAC (paper
section 2.3.2) and the corridor along the planned path where the needle is allowed to enter it.

``fit_head_sphere`` takes millimetres (the fiducials come from CT or camera frames); the
:class:`HeadSphere` and :class:`Corridor` used inside the controller and the safety layer are in
metres. The sphere through the fiducial centres envelops the scalp locally (fiducials sit on
the skin), which is what the paper models; ``margin`` parameters add clearance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monotracker.robot.units import mm_to_m


@dataclass
class SphereFit:
    """Result of :func:`fit_head_sphere` (mm, in the frame of the input points)."""

    ok: bool
    reason: str
    centre_mm: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    radius_mm: float = float("nan")
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    rms_mm: float = float("nan")


def _sphere_lstsq(p: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic least-squares sphere: |x|^2 = 2 c.x + (r^2 - |c|^2)."""
    A = np.hstack([2.0 * p, np.ones((len(p), 1))])
    b = np.sum(p * p, axis=1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = sol[:3]
    r2 = sol[3] + c @ c
    return c, float(np.sqrt(r2)) if r2 > 0 else float("nan")


def fit_head_sphere(
    points_mm: np.ndarray,
    inlier_mm: float = 3.0,
    min_radius_mm: float = 40.0,
    max_radius_mm: float = 200.0,
    iterations: int = 200,
    seed: int = 0,
) -> SphereFit:
    """RANSAC sphere through fiducial centres (mm). Needs >= 4 points not on one plane.

    Minimal samples of 4 points give candidate spheres; a candidate counts only if its radius
    is head-sized (``min_radius_mm``..``max_radius_mm``); the one with most points within
    ``inlier_mm`` of its surface is refined by least squares on its inliers. Deterministic
    (``seed``). Returns ``ok=False`` with a reason when no head-sized sphere explains >= 4 points.
    """
    p = np.asarray(points_mm, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
        return SphereFit(False, "head sphere: points must be a finite (n, 3) array in mm")
    n = len(p)
    if n < 4:
        return SphereFit(False, f"head sphere: need at least 4 fiducials, got {n}")
    rng = np.random.default_rng(seed)
    best: tuple[int, float, np.ndarray] | None = None
    samples = [np.arange(4)] if n == 4 else [rng.choice(n, 4, replace=False) for _ in range(iterations)]
    for idx in samples:
        q = p[idx]
        if abs(np.linalg.det(np.hstack([q[1:] - q[0]]))) < 1e-6 * max(1.0, np.ptp(q) ** 3):
            continue
        c, r = _sphere_lstsq(q)
        if not (np.isfinite(r) and min_radius_mm <= r <= max_radius_mm):
            continue
        res = np.abs(np.linalg.norm(p - c, axis=1) - r)
        inl = np.flatnonzero(res < inlier_mm)
        score = (len(inl), -float(np.sum(res[inl] ** 2)))
        if best is None or score > (best[0], best[1]):
            best = (score[0], score[1], inl)
    if best is None or best[0] < 4:
        return SphereFit(False, "head sphere: no head-sized sphere fits the fiducials (coplanar or scattered points)")
    inl = best[2]
    c, r = _sphere_lstsq(p[inl])
    if not (np.isfinite(r) and min_radius_mm <= r <= max_radius_mm):
        return SphereFit(False, f"head sphere: refined radius {r:.1f} mm is not head-sized")
    res = np.abs(np.linalg.norm(p[inl] - c, axis=1) - r)
    return SphereFit(True, f"sphere through {len(inl)}/{n} fiducials", c, r, inl, float(np.sqrt(np.mean(res**2))))


@dataclass(frozen=True)
class HeadSphere:
    """Head obstacle in the robot base frame (m)."""

    centre_m: np.ndarray
    radius_m: float

    @classmethod
    def from_mm(cls, centre_mm, radius_mm) -> "HeadSphere":
        return cls(np.asarray(mm_to_m(centre_mm), dtype=float), float(mm_to_m(radius_mm)))

    def distance(self, points_m: np.ndarray) -> np.ndarray:
        """Signed distance (m) of ``(n, 3)`` points to the sphere surface (negative inside)."""
        d = np.asarray(points_m, dtype=float).reshape(-1, 3) - self.centre_m
        return np.sqrt((d * d).sum(axis=1)) - self.radius_m


@dataclass(frozen=True)
class Corridor:
    """The planned path as an allowed tube: a cylinder of ``radius_m`` around the target's z axis
    (the needle direction), from far outside down to ``depth_m`` past the target tip position.
    Needle points inside it are exempt from head repulsion and the keep-out check, so the needle
    can reach an entry point that lies on (or inside) the head sphere."""

    radius_m: float = 0.010
    depth_m: float = 0.005

    def contains(self, points_m: np.ndarray, T_base_target: np.ndarray) -> np.ndarray:
        """Boolean (n,): which points lie inside the corridor of ``T_base_target`` (tip pose, m)."""
        p = np.asarray(points_m, dtype=float).reshape(-1, 3) - T_base_target[:3, 3]
        s = p @ T_base_target[:3, 2]
        radial2 = (p * p).sum(axis=1) - s * s
        return (radial2 <= self.radius_m**2) & (s <= self.depth_m)
