"""E-stop from another thread while the control loop is inside a slow arm call."""

import threading
import time

import numpy as np

from monotracker.robot.sim_arm import ManualClock, SimulatedArm
from monotracker.robot.tracker import Tracker
from robot_rig import RATE, offset_target, to_mm


class StallingArm(SimulatedArm):
    """Simulated arm whose next ``command_velocity`` stalls until released (a TCP send that
    hangs); records the order of commands and stops."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.log = []
        self.stall = False
        self.entered = threading.Event()
        self.release = threading.Event()
        self.release_after = 3.0
        self.stall_read = False

    def read(self):
        if self.stall_read:
            self.stall_read = False
            self.entered.set()
            self.release.wait(self.release_after)
        return super().read()

    def command_velocity(self, dq, acceleration):
        if self.stall:
            self.stall = False
            self.entered.set()
            self.release.wait(self.release_after)
        super().command_velocity(dq, acceleration)
        self.log.append(("cmd", np.array(dq)))

    def stop(self, deceleration):
        super().stop(deceleration)
        self.log.append(("stop", deceleration))


def test_estop_latches_at_once_while_the_loop_is_stuck_in_a_send():
    clock = ManualClock()
    arm = StallingArm(clock=clock)
    tr = Tracker(arm=arm, clock=clock, rate_hz=RATE)
    T = offset_target()
    assert tr.connect().ok and tr.arm().ok
    tr.set_target(to_mm(T), clock())
    assert tr.start_tracking().ok
    for _ in range(10):
        tr.set_target(to_mm(T), clock())
        tr.step()
        clock.advance(1 / RATE)
    arm.stall = True
    loop = threading.Thread(target=tr.step)
    loop.start()
    assert arm.entered.wait(2.0)
    t0 = time.monotonic()
    r = tr.estop("operator e-stop")
    waited = time.monotonic() - t0
    assert r.ok
    assert tr.state.value == "estopped"  # latched before the stuck call returns
    assert waited < 0.5, f"e-stop blocked {waited:.2f} s behind the control loop"
    arm.release.set()
    loop.join(3.0)
    assert not loop.is_alive()
    # the command that was in flight when the e-stop latched is followed by a stop
    assert arm.log[-1][0] == "stop"
    assert arm.log[-1][1] == tr.safety.cfg.estop_decel


def test_estop_racing_an_auto_resume_stays_latched():
    """The e-stop latches without the tracker lock, so it can land between a check and a
    transition made by another thread. Simulate it at the worst instant: inside the auto-resume
    of a hold (state checked 'holding', about to go to 'tracking'). The e-stop must win."""
    from robot_rig import Rig

    rig = Rig()
    T = offset_target()
    rig.start(T)
    rig.run(0.1, T)
    rig.run(0.2, T, feed=False)
    assert rig.tracker.state.value == "holding"
    safety = rig.tracker.safety
    real_fresh = safety.target_fresh
    fired = []

    def fresh_with_concurrent_estop(now):
        if not fired:
            fired.append(True)
            rig.tracker.estop("e-stop from the UI thread")
        return real_fresh(now)

    safety.target_fresh = fresh_with_concurrent_estop
    rig.tracker.set_target(to_mm(T), rig.clock())
    assert fired
    assert rig.tracker.state.value == "estopped"
    safety.target_fresh = real_fresh
    n = rig.arm.commands
    rig.run(0.2, T)
    assert rig.tracker.state.value == "estopped" and rig.arm.commands == n


def test_stopping_a_hung_loop_thread_returns_and_estops():
    """Tracker.stop() while the loop thread is stuck in an arm call: it must return (not wait
    for the call) and latch an e-stop, since the loop is no longer in control."""
    arm = StallingArm()
    arm.release_after = 6.0
    tr = Tracker(arm=arm, rate_hz=RATE)
    T = offset_target()
    assert tr.connect().ok and tr.arm().ok
    tr.set_target(to_mm(T), time.monotonic())
    assert tr.start_tracking().ok
    arm.stall_read = True  # read() runs every cycle, whatever the state (no timing needed)
    tr.start()
    try:
        assert arm.entered.wait(2.0)
        t0 = time.monotonic()
        tr.stop()
        took = time.monotonic() - t0
        assert took < 4.0, f"stop() waited {took:.1f} s for the hung arm call"
        assert tr.state.value == "estopped"
        assert "thread" in tr.safety.history[-1].reason
    finally:
        arm.release.set()
