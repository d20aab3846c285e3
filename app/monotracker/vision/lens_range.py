"""Is the camera's lens inside the range the camera path was judged on? (issue 28)

Trust on shaded balls was judged on physically rendered frames (Mitsuba 3, held-out scenes,
docs/vision.md "Other lenses"). With the camera where the layout planner puts it (its closest
distance, :data:`JUDGED_DISTANCE_MM` from the point it aims at):

* the generator's lens (1280 x 720, f = 1100 px) images the kit's 4 mm-radius balls at about 11
  px, and a 1920 x 1080 sensor behind the same optics at about 16.5 px: on their unseen sets no
  pose the session's gate passed to the arm was 1-2 mm off at an 80 mm-deep target;
* a shorter lens (f = 800 px on the same sensor) images them at about 8 px, and on five unseen
  sets 2.6-7.3 % of the poses the gate passed were 1.0-1.3 mm off (none over 2 mm): a small
  ball's contact shadow trips too few of its edge rays for the shading check to see it, and
  from that close the pose is well enough determined that its predicted error no longer covers
  the shading push. The same 8 px balls seen through the long lens from 536 mm were not.

A lens that images the balls under :data:`MIN_BALL_PX` from that distance is *short*
(:func:`short_lens_radius_px`, :func:`is_short`): the layout planner names it in its notes, the
camera rig raises the setup warning ``camera_short_lens``,
``calibrate-camera`` prints it (:func:`short_lens_message`, the one wording), and the pose tracker
covers its balls' shading more strictly (``TrackerConfig.short_lens_band_floor_px``).
10 px lies between the judged 11 px and the short lens's 8 px; nothing between them was measured.
"""

from __future__ import annotations

import numpy as np

#: the smallest image radius (px) of a fiducial ball, at :data:`JUDGED_DISTANCE_MM`, inside the
#: range the camera path was judged on (see the module docstring)
MIN_BALL_PX = 10.0
#: the camera distance (mm, camera to the point it aims at) the lens is judged at: the layout
#: planner's closest (``planning.problem.CameraSpace``'s default ``distance_mm[0]``; a test keeps
#: the two equal)
JUDGED_DISTANCE_MM = 400.0


def ball_radius_px(camera, radius_mm: float, distance_mm: float) -> float:
    """Image radius (px) of a ball of ``radius_mm`` (mm) whose centre lies ``distance_mm`` (mm)
    in front of ``camera`` (a :class:`~.camera_model.CameraModel`) on its optical axis: the
    pinhole's ``f R / sqrt(Z^2 - R^2)`` with f the mean of fx and fy (px)."""
    f = 0.5 * (float(camera.K[0, 0]) + float(camera.K[1, 1]))
    r, z = float(radius_mm), float(distance_mm)
    if not (r > 0 and z > r):
        raise ValueError(f"need 0 < radius < distance, got radius {r:g} mm at {z:g} mm")
    return f * r / float(np.sqrt(z * z - r * r))


def short_lens_radius_px(camera, radius_mm: float, distance_mm: float = JUDGED_DISTANCE_MM) -> float | None:
    """The balls' image radius (px) from ``distance_mm`` (:func:`ball_radius_px`) where it is under
    :data:`MIN_BALL_PX` (a short lens for them), else None; None too for a radius that is no
    ball's (not finite, <= 0, beyond that distance), which the caller's own checks refuse."""
    r, d = float(radius_mm), float(distance_mm)
    if not (np.isfinite(r) and 0.0 < r < d):
        return None
    r_px = ball_radius_px(camera, r, d)
    return r_px if r_px < MIN_BALL_PX else None


def is_short(camera, radius_mm: float) -> bool:
    """Whether ``camera``'s lens is short for balls of ``radius_mm`` (mm) at
    :data:`JUDGED_DISTANCE_MM` (:func:`short_lens_radius_px`)."""
    return short_lens_radius_px(camera, radius_mm) is not None


def short_lens_message(camera, radius_mm: float, distance_mm: float = JUDGED_DISTANCE_MM) -> str:
    """Why ``camera`` (a CameraModel) is outside the judged range for balls of ``radius_mm`` (mm):
    they image under :data:`MIN_BALL_PX` from ``distance_mm`` (mm; the layout planner passes its
    own closest); "" when they do not, or when the radius is no ball's. One line, for the
    operator: the layout planner's notes, the camera setup warning ``camera_short_lens``,
    ``calibrate-camera``."""
    d = float(distance_mm)
    r_px = short_lens_radius_px(camera, radius_mm, d)
    if r_px is None:
        return ""
    return (f"short lens for the fiducial balls: from {d:.0f} mm (the layout planner's closest camera "
            f"distance) this calibration images them at {r_px:.1f} px radius, under the {MIN_BALL_PX:g} px "
            "the camera path was judged with; with balls of 8 px seen that close, 2.6-7.3 % of the poses "
            "passed to the arm on rendered test frames were 1.0-1.3 mm off at the target (none over 2 mm), "
            "and the pose tracker now reads their shading more cautiously (fewer poses trusted). "
            "Use a longer lens or a sensor with more pixels, and check the layout planner's rating")
