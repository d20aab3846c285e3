"""Drive the simulated UR10 with the APFF admittance tracker, behind the safety layer.

What it shows: :class:`monotracker.robot.tracker.Tracker` (public API in millimetres) on the
simulated UR10 stepped on a manual clock at 125 Hz (deterministic; ``tracker.start()`` runs the
same loop on a real-time thread). The needle-tip target starts 30 mm away and then moves at
15 mm/s, as a head would; the script arms, starts tracking, prints the tip error, then feeds a
stale target (the camera stopped) and shows the safety layer holding the arm still, and ends
with an e-stop. Exits non-zero if the arm does not reach the target or keeps moving when held.

Run: ``python examples/05_apff_tracker_sim_ur10.py [--variant APF-A-II|APF-A-I|APF-V]``
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from monotracker.robot import kinematics as kin
from monotracker.robot.sim_arm import ManualClock, SimulatedArm
from monotracker.robot.tracker import Tracker

RATE_HZ = 125.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variant", default="APF-A-II", choices=("APF-A-II", "APF-A-I", "APF-V"))
    args = ap.parse_args(argv)

    clock = ManualClock()
    arm = SimulatedArm(clock=clock)
    tracker = Tracker(arm=arm, clock=clock, variant=args.variant, rate_hz=RATE_HZ)
    # needle-tip pose at the ready configuration, in mm (robot base frame)
    T_start = kin.fk(kin.Q_READY) @ kin.NeedleTool().T_tool0_tip
    T_start[:3, 3] *= 1000.0
    T_goal = T_start.copy()
    T_goal[:3, 3] += [30.0, -20.0, 10.0]

    def target(t: float) -> np.ndarray:            # the head moves +x at 15 mm/s after 3 s
        T = T_goal.copy()
        T[:3, 3] += [15.0 * max(0.0, t - 3.0), 0.0, 0.0]
        return T

    def run(seconds: float, feed: bool = True):
        snap = None
        for _ in range(int(round(seconds * RATE_HZ))):
            if feed:
                tracker.set_target(target(clock()), stamp=clock(), valid=True)
            snap = tracker.step()
            clock.advance(1.0 / RATE_HZ)
            arm.advance_to(clock())
        return snap

    for step in (tracker.connect, tracker.arm):
        r = step()
        print(f"{step.__name__}: {'ok' if r.ok else r.reason}")
    tracker.set_target(target(clock()), stamp=clock(), valid=True)
    r = tracker.start_tracking()
    print(f"start_tracking: {'ok' if r.ok else r.reason}")
    snap = run(3.0)
    print(f"after 3 s: state {snap.state}, tip error {snap.tip_error_mm:.2f} mm, "
          f"axis error {snap.angle_error_deg:.2f} deg")
    reached = snap.tip_error_mm < 1.0
    snap = run(2.0)
    print(f"head moving at 15 mm/s for 2 s: tip error {snap.tip_error_mm:.2f} mm")
    q_before = np.array(arm.read().q)
    snap = run(1.0, feed=False)                   # no new pose: the target goes stale
    q_after = np.array(arm.read().q)
    moved = np.abs(q_after - q_before).max()
    print(f"stale target: state {snap.state}; joints moved {np.degrees(moved):.2f} deg in the last second "
          f"(the safety layer decelerates, then holds)")
    print(f"estop: {tracker.estop('example done').ok}; state {tracker.state.value}")
    return 0 if reached and snap.state == "holding" and moved < np.radians(2.0) else 1


if __name__ == "__main__":
    sys.exit(main())
