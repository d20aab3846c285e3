"""What the layout planner and the camera rig tell the team about a short lens (issue 28).

The rule and its wording are vision's (:mod:`monotracker.vision.lens_range`: balls imaged under
``MIN_BALL_PX`` from the planner's closest camera distance are outside the range the camera path
was judged on); this module asks it at the planner's own distance, for the planner's notes
(``plan-layout``'s report, the app's layout panel) and the camera setup warning
``camera_short_lens``.
"""

from __future__ import annotations

import dataclasses

from monotracker.vision.lens_range import MIN_BALL_PX, ball_radius_px, short_lens_message

from .problem import CameraSpace

__all__ = ["MIN_BALL_PX", "ball_radius_px", "closest_distance_mm", "short_lens"]


def closest_distance_mm() -> float:
    """The layout planner's closest camera distance (mm, camera to the point it aims at): the
    lower end of :class:`~.problem.CameraSpace`'s default ``distance_mm``."""
    field = {f.name: f for f in dataclasses.fields(CameraSpace)}["distance_mm"]
    return float(field.default[0])


def short_lens(camera, radius_mm: float, distance_mm: float | None = None) -> str:
    """Why ``camera`` (a CameraModel) is outside the judged range for balls of ``radius_mm``
    (mm), seen from ``distance_mm`` (None: the planner's closest, :func:`closest_distance_mm`);
    "" when it is inside or the radius is no ball's (the plan's own checks refuse that). One
    line, for the operator (:func:`~monotracker.vision.lens_range.short_lens_message`)."""
    return short_lens_message(camera, radius_mm, closest_distance_mm() if distance_mm is None else float(distance_mm))
