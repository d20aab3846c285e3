"""The "learn the ball colour" command: one click on a ball in a camera frame.

:func:`learn_ball_colour_from_frame` learns the HSV band of the clicked ball (vision's
:func:`~monotracker.vision.ball_colour.learn_ball_colour`), gives it to the running camera's
detector and, when the camera has a calibration file, saves it there (so that the next start
with that file detects the same balls). Every refusal is one line the user can act on.

The click must be on the image the user looked at: a caller that showed a frame passes it
(``frame=``, learned from as is) or its index (``frame_index=``: refused when the camera's newest
frame is another one), never the frame that happens to be newest at click time, which may be
seconds later with the head moved (skin or drape under the pixel). Without either, the newest
frame is used: what a caller that showed nothing (a typed pixel) asked for.
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


def learn_ball_colour_from_frame(rig, calibration_path: str | None, x_px: float, y_px: float, *,
                                 frame=None, frame_index: int | None = None) -> LearnedColour:
    """Learn at pixel (``x_px``, ``y_px``) of ``frame`` (the BGR image the user clicked on) or,
    without it, of ``rig``'s newest frame, refused when ``frame_index`` is given and the newest
    frame is not that one; raises :class:`~monotracker.errors.MonoTrackerError` (or its
    ``InputError``) with the reason."""
    from monotracker.vision.ball_colour import learn_ball_colour
    from monotracker.vision.camera_model import CameraModel

    if rig is None:
        raise MonoTrackerError("no camera running: start the camera, then click a ball")
    if frame is not None:
        image = frame
    else:
        newest = rig.latest_frame()
        if newest is None or newest[0] is None:
            raise MonoTrackerError("no camera frame yet: wait for the live image, then click a ball")
        if frame_index is not None and newest[1] != frame_index:
            raise MonoTrackerError(f"the camera image changed since it was shown (frame {frame_index}, now "
                                   f"{newest[1]}): nothing learned; show it again and click a ball")
        image = newest[0]
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
