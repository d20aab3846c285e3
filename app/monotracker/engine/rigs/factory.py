"""The one factory from a camera or robot spec to a rig.

Camera: the source's row in the table of source kinds (``rigs/sources.py``) builds the rig:

* ``"sim"`` -- :class:`~.sim.SimImageRig`, the digital-twin camera: the simulator renders the
  phantom (exact ray-sphere fiducials, skin, blur, noise) at the session time, placed where the
  OR layout puts the camera (``monotracker.sim.or_layout``); vision's ``PoseTracker`` detects the
  balls and registers them (``registration.register`` with the previous pose as prior). A frame
  reaches the software ``transport_delay_s`` (30 ms) after exposure.
* ``"sim-points"`` -- :class:`~.sim.ProjectedFiducialRig`, the same twin at the level of detected
  points (no rendering, no image detector): exact ellipse centres of the balls + lens distortion
  + 0.15 px noise -> the same pose tracker (vision's, through a point detector). Cheaper; for
  studies of the loop itself.
* ``"device:N" | "file:PATH" | "folder:PATH"`` -- :class:`~.stream.StreamRig`: vision's
  ``PoseStream`` on a real frame source (its own thread; clock="real" only), with the calibration
  file given to ``set_camera`` (``CameraModel.load``) or, without one, vision's default model and
  a warning.
* ``"replay:DIR"`` -- :class:`~.stream.StreamRig` on a session recording
  (``vision.replay_source``), paced at the recorded frame times, with the recording's own
  calibration unless one is given.

Every rig's pose tracker applies the session's per-frame trust rules
(``SessionConfig.frame_rules``: ``min_fiducials``, ``max_predicted_tre_mm``); the loop's gate
judges what the rigs deliver with the same limits: one verdict, built from one configuration.

Both simulated rigs use the CT fiducials *confirmed in the plan* (from the CT detector), not the
phantom's true centres, so CT detection error is part of the measured TRE; their truth (head pose
over time) comes from the OR layout and the simulator's trajectories. Faults (``sim/faults.py``)
are applied to the simulated hardware there.

Robot: the robot-backend table (``robot/backends.py``) gives the arm; clock="real" with
``SessionConfig.control_process`` runs its control loop in its own process
(:class:`~.robot_process.ProcessRobotRig`), otherwise (and always for clock="sim") in-process
(:class:`~.robot.TrackerRobotRig`).

A session given ``camera_factory`` / ``robot_factory`` (tests on doubles) uses those instead;
:func:`build_camera_rig` / :func:`build_robot_rig` are the defaults they may wrap.
"""

from __future__ import annotations

from monotracker.engine.rigs.base import CameraRig, RobotRig
from monotracker.engine.rigs.sources import parse_source
from monotracker.errors import MonoTrackerError


def make_camera_rig(source: str, calibration_path, plan, cfg, session) -> CameraRig:
    """The rig for camera ``source`` on ``plan`` (the session's ``camera_factory`` if it has one)."""
    factory = getattr(session, "camera_factory", None)
    if factory is not None:
        return factory(source, calibration_path, plan, cfg, session)
    return build_camera_rig(source, calibration_path, plan, cfg, session)


def build_camera_rig(source: str, calibration_path, plan, cfg, session) -> CameraRig:
    """The rig the table of source kinds builds for ``source`` (see the module docstring), applying
    the session's per-frame trust rules (``SessionConfig.frame_rules``).
    Raises ``MonoTrackerError`` (one line) for a bad source, or a real camera on the sim clock."""
    kind, arg = parse_source(source)
    if kind.real_clock and cfg.clock != "real":
        raise MonoTrackerError("real cameras need a real-clock session (clock='real')")
    rig = kind.build(arg, calibration_path, plan, cfg, session, cfg.frame_rules(getattr(plan, "ball_finish", None)))
    if kind.simulated:
        rig.clock = session.clock
        rig.nice = int(getattr(cfg, "pose_nice", 0))  # >= 0 (SessionConfig.validate): never above the web server
        rig.camera_process = bool(getattr(cfg, "sim_camera_process", False)) and cfg.clock == "real"
    rig.validation.limit_mm = float(cfg.max_validation_tre_mm)
    _watch_camera_motion(rig, int(getattr(cfg, "camera_motion_every", 0)))
    return rig


def _watch_camera_motion(rig: CameraRig, every: int) -> None:
    """Give the rig's pose tracker a camera-motion watch (``SessionConfig.camera_motion_every``)
    when its frames show the room (``rig.watches_background``): the tracker refuses every pose
    with ``camera_moved`` once the background shows the camera moved after the hand-eye
    calibration, so the arm holds. A new rig (the camera restarted) starts a new reference."""
    tracker = getattr(rig, "tracker", None)
    if every <= 0 or tracker is None or not getattr(rig, "watches_background", False):
        return
    from monotracker.vision.camera_motion import CameraMotionMonitor, DeferredMotionWatch, MotionConfig

    # a due frame's check runs after its pose is given out (the rig calls after_publish), its
    # verdict from the next frame; a frame whose pose jumped is checked on its own path (issue 29)
    tracker.camera_motion = DeferredMotionWatch(CameraMotionMonitor(float(rig.K[0, 0]), MotionConfig(every_n_frames=every)))


def make_robot_rig(cfg, session) -> RobotRig:
    """The robot rig for ``cfg.robot`` (the session's ``robot_factory`` if it has one)."""
    factory = getattr(session, "robot_factory", None)
    if factory is not None:
        return factory(cfg, session)
    return build_robot_rig(cfg, session)


def build_robot_rig(cfg, session) -> RobotRig:
    """clock="real" with ``control_process`` on: the control loop in its own process; otherwise
    (and always for clock="sim") in-process. Raises ``MonoTrackerError`` when it cannot connect."""
    if getattr(cfg, "clock", "sim") == "real" and getattr(cfg, "control_process", False):
        from monotracker.engine.rigs.robot_process import ProcessRobotRig

        return ProcessRobotRig(cfg, session)
    from monotracker.engine.rigs.robot import TrackerRobotRig

    return TrackerRobotRig(cfg, session)
