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

Partial occlusion (not a fault: the loop must keep tracking with >= 4 fiducials) is set on the
camera rig with ``occluded_ids``.
"""

from __future__ import annotations

import numpy as np

from monotracker.geometry import make_transform, rotation_about_axis

FAULTS = ("none", "camera-freeze", "occlude-all", "robot-disconnect", "bad-pose")


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
