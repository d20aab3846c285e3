"""Test doubles for the engine loop's two interfaces (CameraRig, RobotRig).

They let the engine's own logic (gate, holds, alerts, persistence) be tested against the
simulator's truth independently of the vision and robot packages. They are deliberately simple:
the camera double reports the TRUE pose plus Gaussian noise; the robot double moves the tip
towards the target at a bounded speed and stops dead when told to hold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monotracker.engine.rigs.base import CameraRig, PoseSample, RobotRig, RobotStatus
from monotracker.engine.snapshot import CommandResult
from monotracker.geometry import make_transform, rotation_about_axis
from monotracker.sim.or_layout import default_layout


@dataclass
class FakeFrame:
    t_capture: float
    index: int
    T_cam_ct: np.ndarray
    content: int = 0  # stands for the image: the index of the frame it was captured as


class TruthCameraRig(CameraRig):
    def __init__(self, motion="still", noise_mm=0.1, visible=lambda t: 9, seed=0, set_aside=lambda t: {}):
        super().__init__()
        self.set_aside = set_aside      # t -> {fiducial id: px} the estimator left out of the pose
        self.layout = default_layout()
        self.motion = self.layout.motion(motion)
        self.noise_mm = noise_mm
        self.visible = visible
        self.rng = np.random.default_rng(seed)
        self.K = np.array([[1100.0, 0, 640], [0, 1100.0, 360], [0, 0, 1]])
        self.dist = np.zeros(5)
        self.image_size = (1280, 720)
        self.default_T_base_cam = self.layout.T_base_cam
        self._last = None
        self._index = 0

    def truth_T_cam_ct(self, t):
        return self.layout.T_cam_ct(self.motion, t)

    def truth_T_base_ct(self, t):
        return self.layout.T_base_ct(self.motion, t)

    def capture(self, t):
        if self.fault == "camera-freeze" and self._last is not None:
            # a frozen camera as sim/faults.py defines it: the driver keeps delivering, newly
            # stamped, the last frame's content bit for bit
            self._index += 1
            return FakeFrame(t, self._index, self._last.T_cam_ct, self._last.content)
        self._index += 1
        self._last = FakeFrame(t, self._index, self.truth_T_cam_ct(t), self._index)
        return self._last

    def frame_digest(self, frame):
        """The frame's content: equal only for a frozen camera's repeats."""
        return frame.content

    def estimate(self, frame):
        n = 0 if self.fault == "occlude-all" else int(self.visible(frame.t_capture))
        if n < 3:
            return PoseSample(frame.t_capture, frame.index, False, f"{n} fiducials visible", None, n,
                              truth_T_cam_ct=frame.T_cam_ct)
        dT = make_transform(rotation_about_axis(self.rng.normal(size=3), np.radians(0.02)),
                            self.rng.normal(scale=self.noise_mm, size=3))
        if self.fault == "bad-pose":
            dT = make_transform(rotation_about_axis(self.rng.normal(size=3), np.radians(self.rng.uniform(4, 15))),
                                self.rng.uniform(10, 30) * self.rng.choice([-1, 1], size=3))
        T = dT @ frame.T_cam_ct
        return PoseSample(frame.t_capture, frame.index, True, "ok", T, n, fre_mm=0.3, predicted_tre_mm=0.5,
                          truth_T_cam_ct=frame.T_cam_ct, set_aside=dict(self.set_aside(frame.t_capture)))


class FollowerRobotRig(RobotRig):
    """Tip moves straight to the target at <= max_speed_mm_s; holds stop it at once."""

    def __init__(self, max_speed_mm_s=80.0):
        self.layout = default_layout()
        self.state = "disarmed"
        self.connected = True
        self.T_tip = self.layout.planned_needle_pose().copy()
        self.T_tip[:3, 3] += np.array([0.0, 0.0, 60.0])  # parked 60 mm above the entry
        self.target = None
        self.valid = False
        self.stamp = None
        self.max_speed = max_speed_mm_s
        self.speed = 0.0
        self.t_last = None
        self.command_stamp = None
        self.t_command = None

    def _r(self, ok, msg=""):
        return CommandResult(ok, msg)

    def arm(self):
        if self.state == "estopped":
            return self._r(False, "e-stop latched")
        self.state = "armed"
        return self._r(True)

    def disarm(self):
        if self.state != "estopped":
            self.state = "disarmed"
        return self._r(True)

    def start_tracking(self):
        if self.state not in ("armed", "holding"):
            return self._r(False, f"cannot track from {self.state}")
        self.state = "tracking" if self.valid else "holding"
        return self._r(True)

    def stop_tracking(self):
        if self.state in ("tracking", "holding"):
            self.state = "armed"
        return self._r(True)

    def estop(self):
        self.state = "estopped"
        return self._r(True)

    def reset(self):
        if self.state == "estopped":
            self.state = "disarmed"
        return self._r(True)

    def set_target(self, T, stamp, valid, T_base_ct=None):
        self.valid = bool(valid) and T is not None
        if T is not None:
            self.target = np.array(T, float)
        self.stamp = stamp
        if self.state == "tracking" and not self.valid:
            self.state = "holding"
        elif self.state == "holding" and self.valid:
            self.state = "tracking"

    def inject_disconnect(self):
        self.connected = False

    def step(self, now):
        dt = 0.0 if self.t_last is None else now - self.t_last
        self.t_last = now
        self.speed = 0.0
        if not self.connected:
            self.state = "estopped"
            return
        if self.state != "tracking" or self.target is None or dt <= 0:
            return
        d = self.target[:3, 3] - self.T_tip[:3, 3]
        step = min(np.linalg.norm(d), self.max_speed * dt)
        if np.linalg.norm(d) > 0:
            self.T_tip[:3, 3] += d / np.linalg.norm(d) * step
        self.T_tip[:3, :3] = self.target[:3, :3]
        self.speed = step / dt
        self.command_stamp, self.t_command = self.stamp, now

    def status(self):
        return RobotStatus(self.state, self.connected, "" if self.connected else "disconnected",
                           np.zeros(6), np.zeros(6), self.T_tip.copy(), self.speed, self.command_stamp, self.t_command)
