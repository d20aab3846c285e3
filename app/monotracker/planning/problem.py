"""What the layout planner is asked: the head, the plan, the kit, the camera and the room.

Every point and direction is in the CT's frame, LPS millimetres; camera poses are
``T_ct_cam`` (4x4: OpenCV camera frame -> CT mm, i.e. where the camera stands in the CT).

* :class:`HeadSurface` -- the skin as a triangle mesh (``monotracker.ct.head_surface``), with
  outward vertex normals and a ray test (lines of sight blocked by the head itself).
* :class:`Capsule` -- a keep-out volume (a segment with a radius): the robot's tool and arm.
  A camera may not stand inside one; a line of sight through one is blocked.
* :class:`DrapeLine` -- the plane of the drape's edge: skin on the ``normal`` side is exposed,
  the rest is covered (balls there are not seen and new balls may not go there).
* :class:`CameraSpace` -- where a camera may stand: a cone of directions around ``axis`` (from
  the head towards the camera), a distance range (camera to the point it aims at), the
  patient's free side (a half-space), the keep-outs.
* :class:`BallRules` -- where the surgeon allows balls: exposed skin, away from the incision
  (``entry``) and from the path's line, at least ``min_separation_factor`` ball diameters
  apart, optionally inside a cone around ``region_axis``.
* :class:`PlanningProblem` -- all of it, with the target (and entry), the ball radius, the
  camera model and its image noise (px). :meth:`PlanningProblem.problem` names the first
  thing wrong in one line ('' when it can be planned).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monotracker.vision.camera_model import CameraModel

from .detector_defaults import DEFAULT_FOUND_PROBABILITY, DEFAULT_NOISE_PX


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float).reshape(3)
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError("a direction must be a finite non-zero 3-vector")
    return v / n


def _point(v, what: str) -> np.ndarray:
    a = np.asarray(v, float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{what} must be three finite numbers (LPS mm)")
    return a


class HeadSurface:
    """The skin mesh (CT LPS mm) with outward vertex normals and a line-of-sight test.

    Args:
        vertices: (n, 3) float, LPS mm.
        faces: (m, 3) int, wound so that normals point outwards (as ``ct.head_surface`` makes them).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import trimesh

        v = np.asarray(vertices, float).reshape(-1, 3)
        f = np.asarray(faces, np.int64).reshape(-1, 3)
        if len(v) < 4 or len(f) < 4 or not np.all(np.isfinite(v)):
            raise ValueError("the head surface needs at least 4 finite vertices and 4 faces")
        self.mesh = trimesh.Trimesh(vertices=v, faces=f, process=False)
        self.vertices = np.asarray(self.mesh.vertices, float)
        self.normals = np.asarray(self.mesh.vertex_normals, float)
        self.centre = self.vertices.mean(axis=0)

    @classmethod
    def from_mesh(cls, mesh) -> "HeadSurface":
        """From anything with ``vertices`` and ``faces`` (a trimesh, the engine's HeadMesh)."""
        return cls(np.asarray(mesh.vertices), np.asarray(mesh.faces))

    def first_hits(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(n, 3) the first point (mm) where each ray (origin, direction) meets the skin; NaN
        where it misses the head."""
        o = np.asarray(origins, float).reshape(-1, 3)
        out = np.full((len(o), 3), np.nan)
        if len(o) == 0:
            return out
        d = np.asarray(directions, float).reshape(-1, 3)
        d = d / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
        locs, idx, _tri = self.mesh.ray.intersects_location(o, d, multiple_hits=False)
        if len(idx):
            out[np.asarray(idx, int)] = np.asarray(locs, float)
        return out

    def blocked(self, origins: np.ndarray, towards: np.ndarray) -> np.ndarray:
        """(n,) bool: the ray from each origin (mm, just outside the skin: a ball's front
        surface) towards its point (the camera) meets the skin. The camera stands outside the
        head and the ray leaves the skin at its origin, so any hit is one before the camera."""
        o = np.asarray(origins, float).reshape(-1, 3)
        if len(o) == 0:
            return np.zeros(0, bool)
        d = np.asarray(towards, float).reshape(-1, 3) - o
        d = d / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
        return np.asarray(self.mesh.ray.intersects_any(o, d), bool)


@dataclass(frozen=True)
class Capsule:
    """A keep-out volume: every point within ``radius_mm`` of the segment ``a``-``b`` (LPS mm).
    ``name`` says what it is ("robot tool", "robot arm") in reasons."""

    a: np.ndarray
    b: np.ndarray
    radius_mm: float
    name: str = "robot"

    def __post_init__(self):
        object.__setattr__(self, "a", _point(self.a, f"{self.name} keep-out end a"))
        object.__setattr__(self, "b", _point(self.b, f"{self.name} keep-out end b"))
        if not (np.isfinite(self.radius_mm) and self.radius_mm > 0):
            raise ValueError(f"{self.name} keep-out radius must be a positive number of mm")

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(n,) distance (mm) from points (n, 3) to the segment's axis (minus nothing)."""
        p = np.asarray(points, float).reshape(-1, 3)
        ab = self.b - self.a
        t = np.clip(((p - self.a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        return np.linalg.norm(p - (self.a + t[:, None] * ab), axis=1)

    def crosses(self, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """(n,) bool: the segments start-end (n, 3) pass within ``radius_mm`` of the axis."""
        return _segment_distance(np.asarray(starts, float).reshape(-1, 3), np.asarray(ends, float).reshape(-1, 3),
                                 self.a, self.b) < self.radius_mm


def _segment_distance(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """(n,) smallest distance between segments p0-p1 (n, 3) and the segment q0-q1 (3,)."""
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = np.einsum("ij,ij->i", d1, d1)
    e = float(d2 @ d2)
    f = r @ d2
    c = np.einsum("ij,ij->i", d1, r)
    b = d1 @ d2
    denom = a * e - b * b
    s = np.where(denom > 1e-12, np.clip((b * f - c * e) / np.where(denom > 1e-12, denom, 1.0), 0, 1), 0.0)
    t = (b * s + f) / max(e, 1e-12)
    # clamp t and recompute s where t left [0, 1]
    t_c = np.clip(t, 0, 1)
    s = np.where(t != t_c, np.clip((t_c * b - c) / np.maximum(a, 1e-12), 0, 1), s)
    c1 = p0 + s[:, None] * d1
    c2 = q0 + t_c[:, None] * d2
    return np.linalg.norm(c1 - c2, axis=1)


@dataclass(frozen=True)
class DrapeLine:
    """The drape's edge as a plane through ``point`` (LPS mm); skin on the side ``normal``
    points to is exposed. A ball whose centre lies less than ``margin_mm`` above the plane
    counts as under the drape."""

    point: np.ndarray
    normal: np.ndarray
    margin_mm: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "point", _point(self.point, "drape line point"))
        object.__setattr__(self, "normal", _unit(self.normal))

    def height(self, points: np.ndarray) -> np.ndarray:
        """(n,) signed distance (mm) of points above the plane (positive = exposed side)."""
        return (np.asarray(points, float).reshape(-1, 3) - self.point) @ self.normal

    def covers(self, points: np.ndarray) -> np.ndarray:
        return self.height(points) < self.margin_mm


@dataclass(frozen=True)
class CameraSpace:
    """Where the camera may stand (CT LPS mm).

    ``axis``: unit direction from the head towards the nominal camera; ``half_angle_deg``: the
    cone of viewing directions around it; ``distance_mm``: (min, max) from the camera to the
    point it aims at on the head; ``free_side``: if given, the camera stays on the half-space
    ``(camera - head centre) . free_side >= 0`` (the side of the table that is free); ``keep_out``:
    the robot's reach (:class:`Capsule`), which the camera stays ``clearance_mm`` away from and
    which blocks lines of sight; ``aim``: the point the camera looks at (None: the middle of the
    balls it can see, chosen per direction)."""

    axis: np.ndarray
    half_angle_deg: float = 35.0
    distance_mm: tuple = (400.0, 700.0)
    free_side: np.ndarray | None = None
    keep_out: tuple = ()
    clearance_mm: float = 50.0
    aim: np.ndarray | None = None

    def __post_init__(self):
        object.__setattr__(self, "axis", _unit(self.axis))
        if self.free_side is not None:
            object.__setattr__(self, "free_side", _unit(self.free_side))
        if self.aim is not None:
            object.__setattr__(self, "aim", _point(self.aim, "camera aim point"))
        lo, hi = (float(x) for x in self.distance_mm)
        if not (np.isfinite(lo) and np.isfinite(hi) and 100.0 <= lo <= hi <= 3000.0):
            raise ValueError(f"camera distance range must be 100 <= min <= max <= 3000 mm, got {lo:g}-{hi:g}")
        object.__setattr__(self, "distance_mm", (lo, hi))
        if not (np.isfinite(self.half_angle_deg) and 0.0 <= self.half_angle_deg <= 80.0):
            raise ValueError("camera cone half-angle must be 0-80 deg")
        for k in self.keep_out:
            if not isinstance(k, Capsule):
                raise ValueError("keep_out must hold Capsule volumes")

    def where_not(self, eye: np.ndarray, head_centre: np.ndarray) -> str:
        """'' when a camera at ``eye`` (LPS mm) may stand there, else why not (one line)."""
        if self.free_side is not None and (np.asarray(eye) - head_centre) @ self.free_side < 0:
            return "on the patient's occupied side"
        for k in self.keep_out:
            if k.distance(eye)[0] < k.radius_mm + self.clearance_mm:
                return f"inside the {k.name}'s reach"
        return ""


@dataclass(frozen=True)
class BallRules:
    """Where balls may go (besides the skin and the drape): ``incision_clearance_mm`` from the
    entry, ``path_clearance_mm`` from the path's line (entry to target, extended outwards by
    ``path_extension_mm``, where the needle comes in), at least ``min_separation_factor`` ball
    diameters between ball centres (2: twice the ball's size), and, when ``region_axis`` is
    given, within ``region_half_angle_deg`` of it as seen from the head centre (the surgeon's
    allowed region)."""

    incision_clearance_mm: float = 25.0
    path_clearance_mm: float = 15.0
    path_extension_mm: float = 300.0
    min_separation_factor: float = 2.0
    region_axis: np.ndarray | None = None
    region_half_angle_deg: float = 90.0

    def __post_init__(self):
        for name in ("incision_clearance_mm", "path_clearance_mm", "path_extension_mm", "min_separation_factor"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a number >= 0")
        if self.region_axis is not None:
            object.__setattr__(self, "region_axis", _unit(self.region_axis))


@dataclass(frozen=True)
class PlanningProblem:
    """Everything the planner needs (see the module docstring). ``target`` and ``entry`` are
    LPS mm (entry optional); ``radius_mm`` the balls' radius; ``noise_px`` the image noise of
    the ball centres (px, 1-sigma per coordinate); ``edge_rms_px`` the spread of the balls' edge
    fits the pose tracker's shading cover will see (px; None: ``noise_px``, what the default
    edge-fitted detector shows; 0: a detector without an edge fit; :func:`.trust.shading_cover`);
    ``existing`` the fiducials the CT already has ((n, 3) LPS mm centres, may be empty);
    ``drape`` None = nothing covered."""

    head: HeadSurface
    target: np.ndarray
    camera: CameraModel
    space: CameraSpace
    entry: np.ndarray | None = None
    radius_mm: float = 4.0
    noise_px: float = DEFAULT_NOISE_PX
    drape: DrapeLine | None = None
    rules: BallRules = field(default_factory=BallRules)
    existing: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    edge_rms_px: float | None = None
    found_probability: float = DEFAULT_FOUND_PROBABILITY

    def __post_init__(self):
        object.__setattr__(self, "target", _point(self.target, "target"))
        if self.entry is not None:
            object.__setattr__(self, "entry", _point(self.entry, "entry"))
        ex = np.asarray(self.existing, float).reshape(-1, 3)
        if not np.all(np.isfinite(ex)):
            raise ValueError("existing fiducials must be finite LPS mm points")
        object.__setattr__(self, "existing", ex)
        if not (np.isfinite(self.radius_mm) and 0.5 <= self.radius_mm <= 20.0):
            raise ValueError(f"ball radius {self.radius_mm} mm is implausible (0.5-20 mm)")
        if not (np.isfinite(self.noise_px) and 0.005 <= self.noise_px <= 5.0):
            raise ValueError(f"image noise {self.noise_px} px is implausible (0.005-5 px)")
        if self.edge_rms_px is not None and not (np.isfinite(self.edge_rms_px) and 0.0 <= self.edge_rms_px <= 5.0):
            raise ValueError(f"edge spread {self.edge_rms_px} px is implausible (0-5 px)")
        if not (np.isfinite(self.found_probability) and 0.05 <= self.found_probability <= 1.0):
            raise ValueError(f"found probability {self.found_probability} is implausible (0.05-1)")

    @property
    def min_separation_mm(self) -> float:
        """Smallest distance (mm) between two ball centres: the factor times the diameter."""
        return self.rules.min_separation_factor * 2.0 * self.radius_mm

    def problem(self) -> str:
        """'' when this can be planned, else the first thing wrong, in one line."""
        lo, hi = self.head.vertices.min(axis=0), self.head.vertices.max(axis=0)
        if np.any(self.target < lo) or np.any(self.target > hi):
            return "the target lies outside the head surface's extent; check its LPS coordinates"
        if self.head.mesh.is_watertight and not bool(self.head.mesh.contains(self.target[None])[0]):
            return "the target is not inside the head surface"
        if self.entry is not None:
            d = float(np.min(np.linalg.norm(self.head.vertices - self.entry, axis=1)))
            if d > 10.0:
                return f"the entry is {d:.0f} mm from the skin; it must lie on the skin"
            if np.linalg.norm(self.entry - self.target) < 5.0:
                return "entry and target coincide"
        return ""
