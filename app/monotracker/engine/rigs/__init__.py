"""The engine's rigs: what the tracking loop drives, behind two small interfaces.

* ``base.py`` -- :class:`CameraRig` (frames -> :class:`PoseSample`) and :class:`RobotRig`
  (targets -> the arm; :class:`RobotStatus`), in millimetres on this side.
* ``sources.py`` -- the table of camera source kinds (grammar, checks, how each is built).
* ``factory.py`` -- the one factory from a camera or robot spec to a rig.
* ``stream.py`` (real cameras, recordings), ``sim.py`` (the digital twin's cameras),
  ``robot.py`` / ``robot_process.py`` (the arm in-process / in its own control process),
  ``validation.py`` (validation fiducials checked on every estimate).
"""

from monotracker.engine.rigs.base import CameraRig, PoseSample, RobotRig, RobotStatus, estimate_to_sample
from monotracker.engine.rigs.factory import build_camera_rig, build_robot_rig, make_camera_rig, make_robot_rig
from monotracker.engine.rigs.sources import GRAMMAR, SOURCES, parse_source, source_problem

__all__ = ["CameraRig", "PoseSample", "RobotRig", "RobotStatus", "estimate_to_sample", "build_camera_rig",
           "build_robot_rig", "make_camera_rig", "make_robot_rig", "GRAMMAR", "SOURCES", "parse_source",
           "source_problem"]
