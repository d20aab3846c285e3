"""Fault injection for the digital twin: what each fault does to the simulated hardware.

* ``camera-freeze``: the camera keeps handing back its last frame (same index and capture time),
  as a hung USB/GigE driver does; nothing new reaches registration.
* ``occlude-all``: every fiducial is hidden (a drape or a hand over the patch): the frame still
  arrives, with no fiducial in it.
* ``robot-disconnect``: the arm's connection drops (cable, controller reboot): commands no longer
  arrive; a real UR stops on its own (RTDE watchdog / protective stop), the simulated arm does the
  same (``monotracker.robot``'s SimulatedArm).
* ``bad-pose``: the pose pipeline returns confident but wrong poses (as after a wrong fiducial
  assignment): ``ok=True``, plausible FRE, but ``T_cam_ct`` off by 10-30 mm and 4-15 deg,
  different every frame. Only the engine's consistency gate can catch it.

Partial occlusion (not a fault: the loop must keep tracking with >= 4 fiducials) is set on the
camera rig with ``occluded_ids``.
"""

from __future__ import annotations

import numpy as np

from monotracker.geometry import make_transform, rotation_about_axis

FAULTS = ("none", "camera-freeze", "occlude-all", "robot-disconnect", "bad-pose")


def corrupt_pose(T_cam_ct: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A wrong but plausible pose: ``T_cam_ct`` moved 10-30 mm per axis and rotated 4-15 deg
    about a random axis through the CT origin's image (camera frame)."""
    axis = rng.normal(size=3)
    R = rotation_about_axis(axis, np.radians(rng.uniform(4.0, 15.0)))
    t = rng.uniform(10.0, 30.0, size=3) * rng.choice([-1.0, 1.0], size=3)
    return make_transform(R, t) @ np.asarray(T_cam_ct, float)
