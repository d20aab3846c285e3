"""The digital-twin operating room: where the UR10 base, the patient's head and the camera are.

Frames (all millimetres, 4x4 ``T_to_from``):

* ``base``: the UR10 base frame (z up), the room frame of the twin.
* ``ct``: the CT's LPS frame (``monotracker.sim.phantom``).
* ``cam``: the OpenCV camera frame (x right, y down, z forward).

Layout choices (the paper shows a UR10 beside the head and a camera on a stand; numbers are ours):

* The head lies with its fiducial patch facing up: the phantom's ``view_direction_lps`` (centre ->
  fiducial patch) maps to base +z, so the sample path (entry on the patch, target deep) points
  roughly straight down. The planned entry sits at ``entry_base_mm`` = (550, 350, 150) mm: 0.65 m
  from the base axis, 0.15 m above the base, comfortably inside the UR10's 1.3 m reach with the
  needle pointing down.
* The camera stands ``camera_distance_mm`` = 450 mm from the fiducial patch, tilted
  ``camera_tilt_deg`` = 30 deg from the patch normal towards -x of the base (away from the
  robot's side), looking at the patch centre, image "up" towards base +y. From there all nine
  fiducials are in view and the robot coming from above does not stand in the line of sight.

``T_base_cam`` (the hand-eye result the engine uses) follows: ``T_base_cam = T_base_ct0 @ T_ct_cam``.
Head motion is one of vision's trajectories (``monotracker.sim.trajectories``: ``pose(t) ->
T_world_ct`` with world = the CT frame at rest), so the true head pose in the room is
``T_base_ct(t) = T_base_ct0 @ pose(t)`` and the true registration ``T_cam_ct(t) = T_cam_ct0 @ pose(t)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from monotracker.geometry import apply_transform, invert_transform, look_at, make_transform, rotation_about_axis
from monotracker.sim.phantom import HeadPhantom, default_phantom


def _rotation_taking(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector ``a`` onto unit vector ``b``."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    s, c = np.linalg.norm(v), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return rotation_about_axis(perp, np.pi)
    return rotation_about_axis(v, np.arctan2(s, c))


@dataclass(frozen=True)
class ORLayout:
    """The twin's room (see the module docstring). All lengths mm. Derived transforms are
    computed once (``cached_property``); treat the returned arrays as read-only."""

    phantom: HeadPhantom = field(default_factory=default_phantom)
    entry_base_mm: np.ndarray = field(default_factory=lambda: np.array([550.0, 350.0, 150.0]))
    camera_distance_mm: float = 450.0
    camera_tilt_deg: float = 30.0

    @cached_property
    def T_base_ct0(self) -> np.ndarray:
        """Head (CT frame) pose in the robot base at rest."""
        ph = self.phantom
        R = _rotation_taking(ph.view_direction_lps, np.array([0.0, 0.0, 1.0]))
        t = self.entry_base_mm - R @ ph.sample_entry_lps
        return make_transform(R, t)

    @cached_property
    def patch_centre_ct(self) -> np.ndarray:
        """Centroid of the fiducial centres (CT LPS mm): what the camera looks at."""
        return self.phantom.fiducial_centres_lps.mean(axis=0)

    @cached_property
    def T_base_cam(self) -> np.ndarray:
        """Camera pose in the robot base (the hand-eye transform the engine is given)."""
        look = apply_transform(self.T_base_ct0, self.patch_centre_ct)
        tilt = rotation_about_axis(np.array([0.0, 1.0, 0.0]), -np.radians(self.camera_tilt_deg))
        eye = look + tilt @ np.array([0.0, 0.0, self.camera_distance_mm])
        return look_at(eye, look, up=np.array([0.0, 1.0, 0.0]))

    @cached_property
    def head_centre_base(self) -> np.ndarray:
        return apply_transform(self.T_base_ct0, self.phantom.centre_lps)

    def motion(self, name, seed: int = 1):
        """The head trajectory ``name`` (``monotracker.sim.trajectories``); a trajectory object
        (anything with ``pose(t)``) is returned as it is."""
        from monotracker.sim.trajectories import make_trajectory

        if hasattr(name, "pose"):
            return name
        return make_trajectory(name, seed=seed)

    def T_base_ct(self, motion, t: float) -> np.ndarray:
        """True head pose in the base at time ``t`` (s) for a trajectory (``pose(t) -> T_world_ct``)."""
        return self.T_base_ct0 @ motion.pose(t)

    def T_cam_ct(self, motion, t: float) -> np.ndarray:
        """True registration (CT -> camera) at time ``t`` (s)."""
        return self.T_cam_ct0 @ motion.pose(t)

    @cached_property
    def T_cam_ct0(self) -> np.ndarray:
        """True registration with the head at rest."""
        return invert_transform(self.T_base_cam) @ self.T_base_ct0

    def planned_needle_pose(self, t_motion=None, t: float = 0.0) -> np.ndarray:
        """The needle target (tip at entry, +z along the path) in the base for the true head pose."""
        from monotracker.robot.targets import needle_target

        T_cam_ct = self.T_cam_ct0 if t_motion is None else self.T_cam_ct(t_motion, t)
        ph = self.phantom
        return needle_target(self.T_base_cam, T_cam_ct, ph.sample_entry_lps, ph.sample_target_lps)


def default_layout() -> ORLayout:
    return ORLayout()
