"""Fault injection for the digital twin: what each fault does to the simulated hardware.

* ``camera-freeze``: the camera keeps handing back its last frame (same index and capture time),
  as a hung USB/GigE driver does; nothing new reaches registration.
* ``occlude-all``: every fiducial is hidden (a drape or a hand over the patch): the frame still
  arrives, with no fiducial in it.
* ``robot-disconnect``: the arm's connection drops (cable, controller reboot): commands no longer
  arrive; a real UR stops on its own (RTDE watchdog / protective stop), the simulated arm does the
  same (``monotracker.robot``'s SimulatedArm).
* ``bad-pose``: the pose pipeline returns confident but wrong poses (as after a wrong fiducial
  assignment): ``ok=True``, plausible FRE, but the head placed 8-15 mm and 3-8 deg off (rotation
  about the planned entry), different every frame. That is inside the robot safety layer's own
  jump limits (20 mm / 10 deg), so only the engine's consistency gate can catch it.

* ``camera-bump``: someone knocks the camera stand: the camera turns ``BUMP_DEG`` (1.5 deg) and
  shifts ``BUMP_MM`` (3 mm) at once and stays there. The registration is to the camera, so poses
  stay consistent (nothing in the residuals), but the hand-eye ``T_base_cam`` is now wrong and the
  arm follows a path ~12 mm off (1.5 deg at 450 mm).
* ``camera-sag``: the stand's joint creeps: the camera nods down at ``SAG_DEG_PER_S`` (0.1 deg/s)
  from the injection on (up to ``SAG_MAX_DEG``); the arm's error grows ~0.8 mm per second.

Both move the twin camera in the room (:class:`CameraMotion`, given to the simulated camera as
``camera_motion``): the head, the balls and the room-fixed drape behind them all move in the
image as they would; the engine's hand-eye stays as calibrated.

Partial occlusion (not a fault: the loop must keep tracking with >= 4 fiducials) is set on the
camera rig with ``occluded_ids``.
"""

from __future__ import annotations

import numpy as np

from monotracker.geometry import make_transform, rotation_about_axis

#: the faults that move the camera in the room (:class:`CameraMotion`); the rendered twin camera
#: (camera "sim") shows them, the point-level twin ("sim-points") refuses them
CAMERA_MOTION_FAULTS = ("camera-bump", "camera-sag")
FAULTS = ("none", "camera-freeze", "occlude-all", "robot-disconnect", "bad-pose") + CAMERA_MOTION_FAULTS
#: camera-bump: rotation (deg) about ``BUMP_AXIS_CAM`` and shift (mm) along ``BUMP_SHIFT_DIR_CAM``
#: (camera frame: a knock from the side turns the camera mostly about its vertical axis)
BUMP_DEG = 1.5
BUMP_MM = 3.0
BUMP_AXIS_CAM = (0.3, 1.0, 0.1)
BUMP_SHIFT_DIR_CAM = (1.0, 0.2, 0.0)
#: camera-sag: rotation rate (deg/s) about the camera's x axis (the image drifts up: the camera
#: nods down) and its end (deg)
SAG_DEG_PER_S = 0.1
SAG_MAX_DEG = 10.0


def corrupt_pose(T_cam_ct: np.ndarray, rng: np.random.Generator, about_ct: np.ndarray | None = None) -> np.ndarray:
    """A wrong but plausible pose: ``T_cam_ct`` followed by a rotation of 3-8 deg about a random
    axis through the CT point ``about_ct`` (default the CT origin) and a shift of 8-15 mm in a
    random direction (camera frame)."""
    T = np.asarray(T_cam_ct, float)
    p = T[:3, :3] @ (np.zeros(3) if about_ct is None else np.asarray(about_ct, float)) + T[:3, 3]
    R = rotation_about_axis(rng.normal(size=3), np.radians(rng.uniform(3.0, 8.0)))
    d = rng.normal(size=3)
    d *= rng.uniform(8.0, 15.0) / np.linalg.norm(d)
    return make_transform(R, p - R @ p + d) @ T


class CameraMotion:
    """How far the twin camera has moved from where it was calibrated, over time.

    ``T_now_rest(t)`` (4x4, mm) maps a point in the camera frame at rest (where the hand-eye was
    calibrated) into the camera frame at session time ``t`` (s): identity before ``t0``; for
    ``"camera-bump"`` a step (``bump_deg`` about ``BUMP_AXIS_CAM``, ``bump_mm`` along
    ``BUMP_SHIFT_DIR_CAM``; defaults ``BUMP_DEG``, ``BUMP_MM``); for ``"camera-sag"`` a rotation
    about the camera's x axis through its centre growing at ``sag_deg_per_s`` (default
    ``SAG_DEG_PER_S``). Picklable (the twin camera may render in its own process)."""

    def __init__(self, kind: str, t0: float, bump_deg: float = BUMP_DEG, bump_mm: float = BUMP_MM,
                 sag_deg_per_s: float = SAG_DEG_PER_S):
        if kind not in CAMERA_MOTION_FAULTS:
            raise ValueError(f"camera motion must be one of {CAMERA_MOTION_FAULTS}, not {kind!r}")
        self.kind, self.t0 = kind, float(t0)
        self.bump_deg, self.bump_mm, self.sag_deg_per_s = float(bump_deg), float(bump_mm), float(sag_deg_per_s)

    def angle_deg(self, t: float) -> float:
        """Rotation (deg) of the camera from its rest pose at time ``t``."""
        if t < self.t0:
            return 0.0
        if self.kind == "camera-bump":
            return self.bump_deg
        return min(self.sag_deg_per_s * (t - self.t0), SAG_MAX_DEG)

    def T_now_rest(self, t: float) -> np.ndarray:
        if t < self.t0:
            return np.eye(4)
        a = self.angle_deg(t)
        if self.kind == "camera-bump":
            d = np.asarray(BUMP_SHIFT_DIR_CAM, float)
            return make_transform(rotation_about_axis(np.asarray(BUMP_AXIS_CAM, float), np.radians(a)),
                                  self.bump_mm * d / np.linalg.norm(d))
        return make_transform(rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.radians(a)), np.zeros(3))
