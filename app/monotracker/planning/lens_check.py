"""Is this camera's lens inside the range the camera path was judged on? (issue 28)

Trust on shaded balls was judged on physically rendered frames (Mitsuba 3, held-out scenes,
docs/vision.md "Other lenses"). With the camera where the layout planner puts it (its closest
distance, :class:`~.problem.CameraSpace` ``distance_mm[0]``, 400 mm from the point it aims at):

* the generator's lens (1280 x 720, f = 1100 px) images the kit's 4 mm-radius balls at about 11
  px, and a 1920 x 1080 sensor behind the same optics at about 16.5 px: on their unseen sets no
  pose the session's gate passed to the arm was 1-2 mm off at an 80 mm-deep target;
* a shorter lens (f = 800 px on the same sensor) images them at about 8 px, and on five unseen
  sets 2.6-7.3 % of the poses the gate passed were 1.0-1.3 mm off (none over 2 mm): a small
  ball's contact shadow trips too few of its edge rays for the shading check to see it, and
  from that close the pose is well enough determined that its predicted error no longer covers
  the shading push. The same 8 px balls seen through the long lens from 536 mm were not.

So a calibration whose lens images the balls under :data:`MIN_BALL_PX` from that distance is
outside the judged range: the layout planner says so in its notes (its report, the app's layout
panel) and the camera rig as a setup warning while it runs (``camera_short_lens``). It refuses
nothing: the per-frame trust still decides, and the layout planner, given the same camera, rates
its placement (29 % of frames trusted for the short lens against 98 % for the generator's). 10 px
lies between the judged 11 px and the short lens's 8 px; nothing between them was measured.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .problem import CameraSpace

#: the smallest image radius (px) of a fiducial ball, at the planner's closest camera distance,
#: inside the range the camera path was judged on (see the module docstring)
MIN_BALL_PX = 10.0


def closest_distance_mm() -> float:
    """The layout planner's closest camera distance (mm, camera to the point it aims at): the
    lower end of :class:`~.problem.CameraSpace`'s default ``distance_mm``."""
    field = {f.name: f for f in dataclasses.fields(CameraSpace)}["distance_mm"]
    return float(field.default[0])


def ball_radius_px(camera, radius_mm: float, distance_mm: float) -> float:
    """Image radius (px) of a ball of ``radius_mm`` (mm) whose centre lies ``distance_mm`` (mm)
    in front of ``camera`` (a :class:`~monotracker.vision.camera_model.CameraModel`) on its
    optical axis: the pinhole's ``f R / sqrt(Z^2 - R^2)`` with f the mean of fx and fy (px)."""
    f = 0.5 * (float(camera.K[0, 0]) + float(camera.K[1, 1]))
    r, z = float(radius_mm), float(distance_mm)
    if not (r > 0 and z > r):
        raise ValueError(f"need 0 < radius < distance, got radius {r:g} mm at {z:g} mm")
    return f * r / float(np.sqrt(z * z - r * r))


def short_lens(camera, radius_mm: float, distance_mm: float | None = None) -> str:
    """Why ``camera`` (a CameraModel) is outside the judged range for balls of ``radius_mm``
    (mm): they image under :data:`MIN_BALL_PX` from ``distance_mm`` (None: the planner's closest,
    :func:`closest_distance_mm`); "" when it is inside. One line, for the operator."""
    d = closest_distance_mm() if distance_mm is None else float(distance_mm)
    r_px = ball_radius_px(camera, radius_mm, d)
    if r_px >= MIN_BALL_PX:
        return ""
    return (f"short lens for the fiducial balls: from {d:.0f} mm (the layout planner's closest camera "
            f"distance) this calibration images them at {r_px:.1f} px radius, under the {MIN_BALL_PX:g} px "
            "the camera path was judged with; with balls of 8 px seen that close, 2.6-7.3 % of the poses "
            "passed to the arm on rendered test frames were 1.0-1.3 mm off at the target (none over 2 mm). "
            "Use a longer lens or a sensor with more pixels, and check the layout planner's rating")
