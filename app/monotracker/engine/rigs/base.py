"""The rigs' interfaces: what the engine loop asks of a camera rig and of a robot rig.

The loop talks to two small interfaces, so that what vision and robot export can evolve without
touching the loop's logic:

* :class:`CameraRig`: a frame source plus the pose pipeline (detect fiducials, register).
  clock="sim": ``capture(t)`` and ``estimate(frame)`` are called in lock-step by the loop.
  clock="real": ``start()`` runs vision's ``PoseStream`` thread; the loop polls ``poll_frames()``
  and ``latest_sample()``.
* :class:`RobotRig`: the robot ``Tracker`` (safety state machine + APFF controller) and its arm.

Every estimate is normalised into a :class:`PoseSample`, every robot state into a
:class:`RobotStatus` (mm on this side; the robot package converts to metres inside).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monotracker.engine.snapshot import CommandResult
from monotracker.errors import MonoTrackerError


@dataclass
class PoseSample:
    """One pose estimate as the loop sees it.

    ``t_capture`` session clock (s) of the frame; ``t_ready`` when the estimate became available;
    ``T_cam_ct`` 4x4 mm (None when not ok); ``n_matched`` fiducials used; ``fiducial_status``
    id -> "seen"|"newly_lost"|"occluded"|"unknown"; ``residuals_px`` id -> px; ``fre_mm``;
    ``predicted_tre_mm`` at the planned target. Simulator only: ``truth_T_cam_ct`` and
    ``truth_tre_mm`` (error at the planned target vs truth, mm). ``raw``: the package's own
    estimate object (for the UI overlay). ``frame``: what the estimate was computed from (the BGR
    image for image cameras, a :class:`~monotracker.engine.rigs.sim.SimFrame` of points for
    "sim-points"; None when unknown), for session recording."""

    t_capture: float
    frame_index: int
    ok: bool
    reason: str
    T_cam_ct: np.ndarray | None
    n_matched: int
    fiducial_status: dict = field(default_factory=dict)
    residuals_px: dict = field(default_factory=dict)
    fre_mm: float | None = None
    predicted_tre_mm: float | None = None
    t_ready: float | None = None
    truth_T_cam_ct: np.ndarray | None = None
    truth_tre_mm: float | None = None
    raw: object = None
    #: alert code of an invalid estimate as its estimator gives it ("" = none given; e.g.
    #: "frame_size", "camera_ended", "frame_unreadable", "tre_limit"; see vision.pose_stream)
    code: str = ""
    #: fiducials found moved in this frame: plan fiducial id -> estimated shift (mm)
    moved: dict = field(default_factory=dict)
    frame: object = None
    validation: object = None  # registration.validation.ValidationResult, or None (no validation fiducials / no pose)
    #: frames of a still view whose mean the detector read for this estimate (1 = this frame
    #: alone; vision's ``PoseEstimate.averaged_frames``, the opt-in still-view mean)
    averaged_frames: int = 1
    #: fiducials found but left out of this estimate's pose because the other balls put them
    #: beyond their cover: plan fiducial id -> px from where the others put it (vision's
    #: ``PoseEstimate.set_aside``: partly hidden or off for this frame, not moved)
    set_aside: dict = field(default_factory=dict)
    #: where this estimate's time went, wall seconds unless ``*_cpu_s`` (thread CPU time), for
    #: diagnosis and ``benchmarks/pose_latency.py``; empty when the rig does not measure. The
    #: simulated rigs give ``late_s`` (frame started after its camera tick), ``render_s`` /
    #: ``render_cpu_s`` (the twin camera's render), ``arrived_s`` (exposure -> frame in memory),
    #: ``estimate_s`` / ``estimate_cpu_s`` (detection + registration + checks), ``detect_s``,
    #: ``register_s``; the simulated clock: ``pipeline_s`` (the estimate's own compute time) and
    #: ``after_pose_s`` (CPU time of the work run after the pose was given out, e.g. a due
    #: frame's camera-motion check, :meth:`CameraRig.after_publish`; a few us when none ran).
    stages: dict = field(default_factory=dict)


@dataclass
class RobotStatus:
    """``state`` disarmed|armed|tracking|holding|estopped; ``q`` (6,) rad; ``qd`` (6,) rad/s;
    ``T_base_tip`` needle tip pose (4x4, mm, +z along the needle); ``speed_mm_s`` tip speed;
    ``command_stamp`` capture stamp of the target used by the last command and ``t_command``
    when it was sent (session clock s); ``program_fault``: link up but the arm's control
    program stopped (a UR's script: ``"watchdog" | "pendant" | "paused" | "protective_stop" |
    "emergency_stop" | "safeguard_stop" | "not_running"``; "" while it runs), the operator's
    reset restarts it; ``control``: where the control loop runs and with which priority;
    ``response_s``: the arm's command delay + velocity lag (s) where the backend models it (the
    simulated arm in-process), else None."""

    state: str
    connected: bool
    message: str = ""
    q: np.ndarray | None = None
    qd: np.ndarray | None = None
    T_base_tip: np.ndarray | None = None
    speed_mm_s: float = 0.0
    command_stamp: float | None = None
    t_command: float | None = None
    program_fault: str = ""
    control: str = ""
    response_s: float | None = None


class CameraRig:
    """Base class; see the module docstring."""

    K: np.ndarray | None = None
    dist: np.ndarray | None = None
    image_size: tuple | None = None
    default_T_base_cam: np.ndarray | None = None
    #: seconds from the instant a frame is exposed to the moment it reaches the software
    transport_delay_s: float = 0.0

    def __init__(self):
        self.running = False
        self.fault = "none"

    # sim clock
    def capture(self, t: float):
        raise NotImplementedError

    def estimate(self, frame) -> PoseSample:
        raise NotImplementedError

    # real clock
    def start(self) -> None:
        raise NotImplementedError

    def stop(self) -> None:
        pass

    def poll_frames(self) -> list[float]:
        return []

    def poll_frame_info(self) -> list[tuple[float, int | None]]:
        """New frames since the last poll as ``(t_capture, content digest or None)``; the digest
        lets the engine see a frozen camera repeating a frame bit for bit."""
        return [(t, None) for t in self.poll_frames()]

    def frame_digest(self, frame) -> int | None:
        """Checksum of a frame's content (None: this rig cannot tell)."""
        return None

    def latest_sample(self) -> PoseSample | None:
        return None

    def after_publish(self) -> float:
        """Run the work the pose tracker deferred until the last estimate was given out (a due
        frame's camera-motion check, :meth:`~monotracker.vision.pose_tracker.PoseTracker.after_publish`);
        called by the pipeline right after it published the estimate. Returns its CPU time (s);
        never raises (an error of that work is raised by the next estimate)."""
        tracker = getattr(self, "tracker", None)
        run = getattr(tracker, "after_publish", None)
        return 0.0 if run is None else float(run())

    def latest_frame(self):
        return None

    def set_fault(self, name: str) -> None:
        self.fault = name

    def truth_T_cam_ct(self, t: float) -> np.ndarray | None:
        """Simulator truth at time t (None for real cameras)."""
        return None

    def truth_T_base_ct(self, t: float) -> np.ndarray | None:
        """Simulator truth: the head (CT) pose in the robot base at time t, mm (None if real)."""
        return None

    def set_ball_colour(self, colour) -> str:
        """Detect balls of ``colour`` (vision's BallColour) from the next frame on; '' or why not."""
        det = getattr(getattr(self, "tracker", None), "detector", None)
        if det is None or not hasattr(det, "set_colour"):
            return "this camera source has no colour detector (sim-points works on points)"
        det.set_colour(colour)
        return ""


class RobotRig:
    """Base class; see the module docstring."""

    default_T_base_cam: np.ndarray | None = None

    def arm(self) -> CommandResult:
        raise NotImplementedError

    def disarm(self) -> CommandResult:
        raise NotImplementedError

    def start_tracking(self) -> CommandResult:
        raise NotImplementedError

    def stop_tracking(self) -> CommandResult:
        raise NotImplementedError

    def estop(self) -> CommandResult:
        """Latch the e-stop and wait (bounded) for the controller to confirm it."""
        raise NotImplementedError

    def signal_estop(self) -> None:
        """The stop channel: latch the e-stop without waiting for anything the engine or vision
        may hold (safe on the web server's event loop; ``engine/pipeline_priority.py``). Rigs
        whose controller runs elsewhere override it; here it is :meth:`estop`."""
        self.estop()

    def drain_transitions(self) -> list | None:
        """The state transitions (``engine.robot_transitions.RobotTransition``) since the last
        call, in the order the controller made them, each with its own reason; None when this
        rig does not report them (the engine then records the state changes it sees)."""
        return None

    def reset(self) -> CommandResult:
        raise NotImplementedError

    def set_target(self, T_base_target_mm, stamp: float, valid: bool, T_base_ct=None) -> None:
        """New needle target (4x4 mm); ``T_base_ct`` (mm) is the head pose it came from (for
        obstacles that move with the head)."""
        raise NotImplementedError

    def step(self, now: float) -> None:
        raise NotImplementedError

    def start_thread(self) -> None:
        pass

    def status(self) -> RobotStatus:
        raise NotImplementedError

    def inject_disconnect(self) -> None:
        raise MonoTrackerError("this robot cannot simulate a disconnect")

    def close(self) -> None:
        pass


def _nan_to_none(v) -> float | None:
    return None if v is None or not np.isfinite(v) else float(v)


def estimate_to_sample(est, fiducial_ids: list[int]) -> PoseSample:
    """vision's PoseEstimate -> PoseSample (statuses and residuals keyed by plan fiducial id)."""
    status = {fiducial_ids[j]: s for j, s in enumerate(est.status) if j < len(fiducial_ids)}
    res = {fiducial_ids[j]: float(r) for j, r in enumerate(np.asarray(est.residuals_px, float))
           if j < len(fiducial_ids) and np.isfinite(r)}
    reason = est.reason or "ok"
    return PoseSample(
        t_capture=float(est.t_capture), frame_index=int(est.frame_index), ok=bool(est.ok), reason=reason,
        T_cam_ct=None if est.T_cam_ct is None else np.array(est.T_cam_ct, float), n_matched=int(est.n_matched),
        fiducial_status=status, residuals_px=res, fre_mm=_nan_to_none(est.fre_mm),
        predicted_tre_mm=_nan_to_none(est.predicted_tre_mm), raw=est, code=getattr(est, "code", ""),
        moved={fiducial_ids[j]: float(mm) for j, mm in getattr(est, "moved", []) if j < len(fiducial_ids)},
        averaged_frames=int(getattr(est, "averaged_frames", 1)),
        set_aside={fiducial_ids[j]: float(px) for j, px in getattr(est, "set_aside", []) if j < len(fiducial_ids)})
