import numpy as np

from monotracker.geometry import rotation_about_axis
from monotracker.robot import kinematics as kin
from monotracker.robot.sim_arm import ManualClock, SimulatedArm
from monotracker.robot.tracker import Tracker

RATE = 125.0


def ready_tip_pose() -> np.ndarray:
    """Needle tip pose (m) at the ready configuration."""
    return kin.fk(kin.Q_READY) @ kin.NeedleTool().T_tool0_tip


def offset_target(dp_m=(0.03, -0.02, 0.02), rot_deg=5.0) -> np.ndarray:
    T = ready_tip_pose()
    T[:3, 3] += dp_m
    T[:3, :3] = rotation_about_axis([1, 0, 0], np.radians(rot_deg)) @ T[:3, :3]
    return T


def to_mm(T):
    T = np.array(T, dtype=float)
    T[:3, 3] *= 1000.0
    return T


class Rig:
    """A tracker on a simulated arm with a manual clock."""

    def __init__(self, variant="APF-A-II", **kw):
        self.clock = ManualClock()
        self.arm = SimulatedArm(clock=self.clock)
        self.events = []
        self.tracker = Tracker(arm=self.arm, clock=self.clock, variant=variant, rate_hz=RATE,
                               on_event=lambda k, p: self.events.append((k, p)), **kw)

    def run(self, seconds, target_m=None, feed=True, valid=True):
        """Step for ``seconds``; feeds ``target_m`` (callable of t or array) every step if ``feed``."""
        snaps = []
        for _ in range(int(round(seconds * RATE))):
            if feed and target_m is not None:
                T = target_m(self.clock()) if callable(target_m) else target_m
                self.tracker.set_target(to_mm(T), self.clock(), valid)
            snaps.append(self.tracker.step())
            self.clock.advance(1.0 / RATE)
            self.arm.advance_to(self.clock())
        return snaps

    def start(self, target_m):
        assert self.tracker.connect().ok
        assert self.tracker.arm().ok
        self.tracker.set_target(to_mm(target_m), self.clock())
        r = self.tracker.start_tracking()
        assert r.ok, r.reason


