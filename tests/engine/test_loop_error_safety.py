"""An exception in the engine loop must never leave the arm tracking, even when the hold fails."""

from monotracker.engine.loop.clocks import RealThread

from .doubles import FollowerRobotRig


class _BrokenTargetRobot(FollowerRobotRig):
    def set_target(self, T, stamp, valid, T_base_ct=None):
        raise RuntimeError("robot link broke")


def test_failed_hold_after_engine_error_stops_tracking(make_session):
    s = make_session()
    loop = s._loop
    robot = _BrokenTargetRobot()
    robot.state = "tracking"
    loop.robot.rig = robot
    RealThread(loop).on_iteration_error()       # must not raise
    assert robot.state != "tracking"


def test_engine_error_holds_and_alarms(make_session):
    s = make_session()
    loop = s._loop
    robot = FollowerRobotRig()
    robot.state, robot.valid = "tracking", True
    loop.robot.rig = robot
    RealThread(loop).on_iteration_error()
    assert robot.state == "holding" and not robot.valid
    assert loop.holding_code == "engine_error"
