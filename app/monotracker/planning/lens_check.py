"""What the layout planner and the camera rig tell the team about a short lens (issue 28).

The rule is vision's (:mod:`monotracker.vision.lens_range`: balls imaged under ``MIN_BALL_PX``
from the planner's closest camera distance are outside the range the camera path was judged
on); this module words it for the operator: the planner's notes (``plan-layout``'s report, the
app's layout panel) and the camera setup warning ``camera_short_lens``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from monotracker.vision.lens_range import MIN_BALL_PX, ball_radius_px, short_lens_radius_px

from .problem import CameraSpace

__all__ = ["MIN_BALL_PX", "ball_radius_px", "closest_distance_mm", "short_lens"]


def closest_distance_mm() -> float:
    """The layout planner's closest camera distance (mm, camera to the point it aims at): the
    lower end of :class:`~.problem.CameraSpace`'s default ``distance_mm``."""
    field = {f.name: f for f in dataclasses.fields(CameraSpace)}["distance_mm"]
    return float(field.default[0])


def short_lens(camera, radius_mm: float, distance_mm: float | None = None) -> str:
    """Why ``camera`` (a CameraModel) is outside the judged range for balls of ``radius_mm``
    (mm): they image under ``MIN_BALL_PX`` from ``distance_mm`` (None: the planner's closest,
    :func:`closest_distance_mm`); "" when it is inside. One line, for the operator."""
    d = closest_distance_mm() if distance_mm is None else float(distance_mm)
    r = float(radius_mm)
    if not (np.isfinite(r) and 0.0 < r < d):
        return ""                     # no ball's radius: the plan's own checks refuse it
    r_px = short_lens_radius_px(camera, r, d)
    if r_px is None:
        return ""
    return (f"short lens for the fiducial balls: from {d:.0f} mm (the layout planner's closest camera "
            f"distance) this calibration images them at {r_px:.1f} px radius, under the {MIN_BALL_PX:g} px "
            "the camera path was judged with; with balls of 8 px seen that close, 2.6-7.3 % of the poses "
            "passed to the arm on rendered test frames were 1.0-1.3 mm off at the target (none over 2 mm), "
            "and the pose tracker now reads their shading more cautiously (fewer poses trusted). "
            "Use a longer lens or a sensor with more pixels, and check the layout planner's rating")
