"""RobotRig on the robot package's Tracker (filled in when it lands)."""

from monotracker.errors import MonoTrackerError


def make_tracker_rig(cfg, session):
    raise MonoTrackerError("the robot package (Tracker, arms) is not available in this build yet")
