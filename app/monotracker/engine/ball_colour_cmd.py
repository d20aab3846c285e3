"""The "learn the ball colour" command: one click on a ball in the newest camera frame.

:func:`learn_ball_colour_from_frame` learns the HSV band of the clicked ball (vision's
:func:`~monotracker.vision.ball_colour.learn_ball_colour`), gives it to the running camera's
detector and, when the camera has a calibration file, saves it there (so that the next start
with that file detects the same balls). Every refusal is one line the user can act on.
"""

from __future__ import annotations

from dataclasses import dataclass

from monotracker.errors import MonoTrackerError


@dataclass
class LearnedColour:
    """``colour`` (BallColour), ``saved_to`` (calibration file path or None), ``message``."""

    colour: object
    saved_to: str | None
    message: str


def learn_ball_colour_from_frame(rig, calibration_path: str | None, x_px: float, y_px: float) -> LearnedColour:
    """Learn from ``rig``'s newest frame at pixel (``x_px``, ``y_px``); raises
    :class:`~monotracker.errors.MonoTrackerError` (or its ``InputError``) with the reason."""
    from monotracker.vision.ball_colour import learn_ball_colour
    from monotracker.vision.camera_model import CameraModel

    if rig is None:
        raise MonoTrackerError("no camera running: start the camera, then click a ball")
    frame = rig.latest_frame()
    if frame is None:
        raise MonoTrackerError("no camera frame yet: wait for the live image, then click a ball")
    image = frame[0]
    colour = learn_ball_colour(image, (x_px, y_px))
    why = rig.set_ball_colour(colour) if hasattr(rig, "set_ball_colour") else "this camera cannot change colour"
    if why:
        raise MonoTrackerError(f"ball colour learned but not applied: {why}")
    saved = None
    if calibration_path:
        model = CameraModel.load(calibration_path)
        model.ball_colour = colour
        model.save(calibration_path)
        saved = str(calibration_path)
    band = f"hue {colour.hue_lo}-{colour.hue_hi}, saturation >= {colour.sat_min}, value >= {colour.val_min}"
    where = f"saved in {saved}" if saved else "not saved (no calibration file: it lasts until the camera restarts)"
    return LearnedColour(colour, saved, f"ball colour set: {band}; {where}")
