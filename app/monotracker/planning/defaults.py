"""A planning problem from what a CT and a plan say, when nobody has described the room.

Choices written down (all CT LPS mm):

* **camera axis**: from the head's centre towards the CT's fiducials (their centroid, when there
  are at least 4), else towards the entry, else towards the target: the side the team works on;
* **cone and distances**: 35 deg around it, 400-700 mm from the head (a camera on a stand);
* **drape line**: the plane through the head's centre perpendicular to the axis, so the half of
  the head facing the camera is exposed, ``drape_offset_mm`` higher (positive: less exposed);
* **robot's reach**: with an entry, two capsules around the path's line outside the entry: the
  needle holder (15 mm radius, 15-150 mm out) and the robot's wrist and arm above it (60 mm
  radius, 150-450 mm out); the camera stays 50 mm clear of them and they block the lines of
  sight through them.
"""

from __future__ import annotations

import numpy as np

from monotracker.vision.camera_model import CameraModel, default_camera

from .detector_defaults import DEFAULT_FOUND_PROBABILITY
from .problem import DEFAULT_NOISE_PX, BallRules, CameraSpace, Capsule, DrapeLine, HeadSurface, PlanningProblem

#: (name, radius mm, from mm, to mm along the path's line outside the entry)
ROBOT_PARTS = (("needle holder", 15.0, 15.0, 150.0), ("robot", 60.0, 150.0, 450.0))


def default_axis(head: HeadSurface, target, entry=None, existing=None) -> np.ndarray:
    """Unit direction from the head's centre towards the side the team works on (see above)."""
    ex = np.zeros((0, 3)) if existing is None else np.asarray(existing, float).reshape(-1, 3)
    if len(ex) >= 4:
        p = ex.mean(axis=0)
    elif entry is not None:
        p = np.asarray(entry, float)
    else:
        p = np.asarray(target, float)
    v = p - head.centre
    if np.linalg.norm(v) < 1.0:
        v = np.array([0.0, 0.0, 1.0])
    return v / np.linalg.norm(v)


def robot_keep_out(entry, target, parts: tuple = ROBOT_PARTS) -> tuple:
    """The robot along the path's line outside the entry (see above): a tuple of capsules."""
    entry = np.asarray(entry, float)
    out = entry - np.asarray(target, float)
    out = out / np.linalg.norm(out)
    return tuple(Capsule(entry + a * out, entry + b * out, r, name) for name, r, a, b in parts)


def build_problem(head: HeadSurface, target, *, entry=None, existing=None, radius_mm: float = 4.0,
                  camera: CameraModel | None = None, noise_px: float = DEFAULT_NOISE_PX, axis=None,
                  half_angle_deg: float = 35.0, distance_mm: tuple = (400.0, 700.0),
                  drape_offset_mm: float | None = 0.0, keep_out: tuple | None = None,
                  rules: BallRules | None = None, edge_rms_px: float | None = None,
                  found_probability: float | None = None) -> PlanningProblem:
    """A :class:`~.problem.PlanningProblem` with the defaults of the module docstring for what
    is not given. ``drape_offset_mm`` None: no drape; ``keep_out`` None: the robot's capsules when
    there is an entry (:func:`robot_keep_out`); ``edge_rms_px``: the shading cover's edge spread
    (:class:`~.problem.PlanningProblem`; None: the noise); ``found_probability`` each seen ball's
    chance of being found (None: the measured default, :mod:`.detector_defaults`)."""
    ax = default_axis(head, target, entry, existing) if axis is None else np.asarray(axis, float)
    if keep_out is None:
        keep_out = robot_keep_out(entry, target) if entry is not None else ()
    space = CameraSpace(ax, half_angle_deg, tuple(distance_mm), keep_out=tuple(keep_out))
    drape = None
    if drape_offset_mm is not None:
        drape = DrapeLine(head.centre + float(drape_offset_mm) * space.axis, space.axis)
    return PlanningProblem(head=head, target=np.asarray(target, float), camera=camera or default_camera(),
                           space=space, entry=None if entry is None else np.asarray(entry, float),
                           radius_mm=float(radius_mm), noise_px=float(noise_px), drape=drape,
                           rules=rules or BallRules(),
                           existing=np.zeros((0, 3)) if existing is None else np.asarray(existing, float),
                           edge_rms_px=None if edge_rms_px is None else float(edge_rms_px),
                           found_probability=DEFAULT_FOUND_PROBABILITY if found_probability is None
                           else float(found_probability))
