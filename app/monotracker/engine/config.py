"""Session configuration (see ``session.py``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from monotracker.errors import InputError

from monotracker.sim.faults import FAULTS  # noqa: F401  (one list, owned by the twin)

TRAJECTORIES = ("still", "drift", "breathing", "jumps")


@dataclass
class SessionConfig:
    """How a session is set up.

    ``home``: folder for ``plan.json``, ``audit.sqlite`` and logs (None = ``paths.data_dir()``).
    ``camera``: ``"sim"`` (rendered digital-twin camera) ``| "sim-points"`` (twin at the level of
    detected points) ``| "device:0" | "file:/path/video.mp4" | "folder:/path" | "replay:/path"`` (a
    session recording, ``monotracker.engine.recording``).
    ``trajectory``: simulated head motion (``"still" | "drift" | "breathing" | "jumps"``, see
    ``monotracker.sim.trajectories``, or a trajectory object with ``pose(t)``; sim only).
    ``robot``: ``"sim" | "ur:<ip>"``. ``arm_pin``: the operator PIN that ``arm(pin)`` checks.
    ``clock``: ``"real"`` (threads, wall time; the web app) or ``"sim"`` (no threads: a driver
    calls ``Session.advance(dt)``, camera, registration and control run in lock-step on a
    simulated clock; the headless demo, tests and benchmark).
    ``camera_fps``: simulated camera frame rate (Hz). ``control_hz``: tracker rate (Hz; 125 Hz as
    a UR CB3). ``seed``: simulator noise seed.

    Loop gates (choices the paper leaves open, written down here):
    ``min_fiducials`` (4): fewer visible fiducials -> hold. ``max_fre_mm`` (1.5): a registration
    whose fiducial residual exceeds this is not trusted. ``max_pose_age_s`` (0.15): the controller
    holds when the freshest trusted pose is older than this (capture time to now: 30 ms camera
    transport + up to one 33 ms frame period + registration, with margin for a loaded machine). ``freeze_after_s`` (0.1): no new
    camera frame for this long -> the arm holds, reported as ``camera_late`` while new frames
    still come (a busy machine: shown once it lasts, one episode per busy spell) and as
    ``camera_stalled`` after ``stall_after_s`` (0.5 s; at least ``freeze_after_s``) without any
    new frame (a camera that stopped delivering); ``camera_freeze`` is a camera that repeats its
    frames bit for bit (held at the first repeat). ``max_jump_mm`` (5.0) / ``max_jump_deg``
    (3.0): a pose that moved more than this from the last trusted one (per frame) is not trusted
    until ``confirm_frames`` (3) consecutive estimates agree with each other (a real head jump is
    followed after a short hold; a single wrong pose never moves the arm).
    ``max_predicted_tre_mm`` (1.0): a pose whose predicted error at the planned target (image
    noise estimated online from the residuals, propagated through the pose covariance) exceeds
    this is not trusted. ``tre_confidence`` (0 = off): when set (0.5-0.999, e.g. 0.95), a pose is
    trusted only when its error at the target stays within ``max_predicted_tre_mm`` with this
    probability by its own predicted distribution, not only its RMS (vision's
    ``max_not_right_probability``: with the RMS limit alone ~7 % of trusted poses exceed it
    even with ideal centres; 0.95 costs about half of the trusted scenes on the rendered frames,
    docs/vision.md). ``ball_finish`` ("read"): what the team says of the kit's balls, "read" (each
    frame's highlight decides), "matte" or "glossy" (vision's ``TrackerConfig.ball_finish``:
    glossy balls beside their contact shadows get a wider error cover with 6 or fewer in view;
    "glossy" also for a far camera whose highlights are too small to read, and the layout planner
    then predicts with that cover). ``camera_adapt``: "" or the user's explicit statement that a real camera
    runs the calibrated sensor binned or cropped (``"bin:2"``, ``"scale:0.5"``,
    ``"crop:X,Y,W,H"``); without it a frame whose size differs from the calibration is refused.
    ``max_validation_tre_mm`` (1.5): arming is refused while any validation fiducial (a fiducial
    the plan keeps out of the fit) is further than this from its viewing ray, or not seen
    (``engine/verification.py`` says why 1.5 mm).
    ``resume_dwell_s`` (0.3): hysteresis; after a stale pose stream or a frozen camera, tracking
    resumes only once trusted poses have been arriving fresh (each younger than
    ``max_pose_age_s`` when it arrives, no gap) for this long; entering the hold is immediate. A stream that
    fails again within 10 s of resuming doubles the dwell (up to 4x) until it is steady for 10 s.
    ``start_wait_s`` (1.0, real clock): ``start_tracking`` waits up to this long for a fresh
    trusted pose while trusted poses keep arriving, instead of refusing a click that fell between
    two frames on a loaded machine.
    ``controller``: the APFF variant (``"APF-V" | "APF-A-I" | "APF-A-II"``, paper section 2.3).
    ``predict_target`` (True): the robot tracker's latency compensation (a Kalman filter on the
    stamped pose stream extrapolated over the measured latency, with its own bounds: capped
    horizon, speed and offset, reset on jumps, gaps, occlusion and holds; ``robot/prediction.py``;
    not in the paper). On by default since it was shown safe under jumps, occlusion, a frozen
    camera and stale poses (``tests/robot/test_prediction.py``,
    ``tests/engine/test_prediction_default.py``) and cuts the tip error on a head moving at
    15 mm/s from ~1.9 to ~0.4 mm; False gives the paper's controller alone.
    ``benchmarks/robot_control.py`` and ``benchmarks/closed_loop.py`` measure both.
    ``control_process`` (True): with clock="real", the robot's control loop (tracker, safety, arm)
    runs in its own process at real-time priority where the OS allows, so vision, UI and logging
    cannot delay it (``robot/control_process.py``); False: a thread in the engine process.
    clock="sim" always steps it in-process (deterministic).
    ``camera_optics`` (None): how the simulated camera (``camera="sim"``) makes its frames: None =
    the simple render (cheap: the live default); a preset of ``monotracker.sim.optics.PRESETS``
    (``"photo"``: gloss, lens blur, Bayer mosaic, raw sensor noise, JPEG 85, drapes and gloves;
    ``"degraded"``: more blur and noise, JPEG 70; ``"sharp"``) = photo-like frames, ~40 ms more
    per frame (``docs/vision.md``). Refused for any other camera (it would change nothing).
    ``pose_nice`` (0): with clock="real", the nice value of the pose pipeline's thread and of the
    simulated camera process: 0 (normal) or higher (below the web server); never negative, and
    ``pose_rt_priority`` only 0: real-time scheduling is for the robot's control process only
    (the policy: ``engine/pipeline_priority.py``; other values are refused with that reason).
    ``camera_motion_every`` (6): rigs whose frames show the room (camera "sim", devices, files,
    replays; not "sim-points") give their pose tracker a camera-motion watch
    (:class:`~monotracker.vision.camera_motion.CameraMotionMonitor`, quarter resolution) that
    checks the static background every this many frames: a camera bumped or sagging after the
    hand-eye calibration refuses every pose (``camera_moved``, the arm holds) until the camera is
    restarted. 6 frames at 30 fps: a knock is refused within 0.2 s, a sag over 0.1 deg within
    0.4 s of reaching it, for ~0.5 ms per frame on average (``benchmarks/pose_rate.py``); 0 = not
    watched.
    ``compute_charge_s`` (None): clock="sim" only: what the simulated clock charges each estimate
    (detection + registration) as compute time, s. None (the default) = its measured CPU time
    (``time.thread_time()`` of the stepping thread: slow registration shows as pose age and
    latency); a number >= 0 = exactly that for every estimate, so that a test of the loop's logic
    (faults, holds, recordings) gives the same figures whatever else the machine runs. Refused
    with clock="real" (the real clock charges what the time really was).
    ``freeze_heap`` (True): while a camera runs, Python's garbage collector walks only the objects
    made since it started (``engine/loop/heap.py``: a full collection of the whole heap stops
    every thread for 60-90 ms, a pose that late holds the arm); False leaves the collector alone.
    ``extra``: free-form settings for experiments; nothing in the engine reads it.

    Units: mm, s, Hz, deg as the names say. :meth:`validate` (called by ``Session``) raises
    :class:`InputError` with one line for an unknown trajectory, clock, camera, robot spec,
    controller, ``camera_adapt`` kind or ``camera_optics`` preset, a non-positive rate or gate, ``min_fiducials`` < 3, or
    an empty ``arm_pin``.
    """

    home: Path | None = None
    camera: str = "sim"
    trajectory: str = "breathing"
    robot: str = "sim"
    arm_pin: str = "1234"
    clock: str = "real"
    camera_fps: float = 30.0
    control_hz: float = 125.0
    seed: int = 0
    min_fiducials: int = 4
    max_fre_mm: float = 1.5
    max_pose_age_s: float = 0.15
    freeze_after_s: float = 0.1
    stall_after_s: float = 0.5
    max_jump_mm: float = 5.0
    max_jump_deg: float = 3.0
    confirm_frames: int = 3
    resume_dwell_s: float = 0.3
    start_wait_s: float = 1.0
    controller: str = "APF-A-II"
    predict_target: bool = True
    max_predicted_tre_mm: float = 1.0
    tre_confidence: float = 0.0
    ball_finish: str = "read"
    camera_adapt: str = ""
    control_process: bool = True
    max_validation_tre_mm: float = 1.5
    camera_optics: str | None = None
    #: Longest a CT job (load + fiducial detection + surface) may run, s; then it is stopped
    #: with a one-line message and the previous CT and plan stay (engine/ct_job.py).
    ct_job_timeout_s: float = 600.0
    pose_nice: int = 0
    pose_rt_priority: int = 0
    sim_camera_process: bool = True
    camera_motion_every: int = 6
    #: the detector reads the mean of up to this many frames of a still view (vision's
    #: ``TrackerConfig.average_still_frames``; 0 = off, the default; opt-in: on dim, noisy
    #: frames it finds more whole balls, and costs 1-2.5 ms a frame at 720p, benchmarks/pose_rate.py
    #: --average; given only while the camera's noise is at least vision's
    #: ``average_min_noise_dn``, 1.8 grey levels; docs/vision.md "A still view's frames averaged")
    average_still_frames: int = 0
    compute_charge_s: float | None = None
    freeze_heap: bool = True
    extra: dict = field(default_factory=dict)

    def frame_rules(self, plan_finish: str | None = None):
        """The per-frame trust rules (vision's :class:`~monotracker.vision.tracker_config.TrackerConfig`)
        every camera rig's pose tracker applies: this session's ``min_fiducials``,
        ``max_predicted_tre_mm`` (mm), ``tre_confidence`` (the chance of exceeding that limit
        at most ``1 - tre_confidence``; 0 = no such rule) and the balls' finish: the plan's
        (``plan_finish``, ``Plan.ball_finish``, set for the patient's kit) or, when the plan
        states none (None), ``ball_finish``; vision's defaults for the rest. A new
        object on each call (a rig's tracker may keep state on it). The loop's gate
        (``engine/loop/gate.py``) judges what the rigs deliver with the same limits: one verdict
        from one configuration."""
        from monotracker.vision.tracker_config import TrackerConfig

        c = float(self.tre_confidence)
        return TrackerConfig(min_fiducials=int(self.min_fiducials), max_predicted_tre_mm=float(self.max_predicted_tre_mm),
                             right_mm=float(self.max_predicted_tre_mm),
                             max_not_right_probability=1.0 - c if c > 0 else 1.0,
                             ball_finish=str(self.ball_finish if plan_finish is None else plan_finish),
                             average_still_frames=int(self.average_still_frames))

    def validate(self) -> None:
        """Raise :class:`InputError` with one line for a bad setting."""
        if not (self.trajectory in TRAJECTORIES or hasattr(self.trajectory, "pose")):
            raise InputError(f"unknown trajectory {self.trajectory!r}; use one of {', '.join(TRAJECTORIES)}")
        if self.clock not in ("real", "sim"):
            raise InputError(f"clock must be 'real' or 'sim', not {self.clock!r}")
        from monotracker.engine.rigs.sources import source_problem

        why = source_problem(self.camera)
        if why:
            raise InputError(why)
        from monotracker.robot.backends import spec_problem

        why = spec_problem(self.robot)
        if why:
            raise InputError(why)
        if self.camera_fps <= 0 or self.control_hz <= 0:
            raise InputError("camera_fps and control_hz must be positive")
        if not (self.freeze_after_s > 0 and self.stall_after_s > 0):
            raise InputError("freeze_after_s and stall_after_s must be positive numbers of seconds")
        if not (self.max_validation_tre_mm > 0):
            raise InputError("max_validation_tre_mm must be positive")
        if self.min_fiducials < 3:
            raise InputError("min_fiducials must be at least 3 (a rigid pose needs 3 points)")
        if self.controller not in ("APF-V", "APF-A-I", "APF-A-II"):
            raise InputError(f"controller must be APF-V, APF-A-I or APF-A-II, not {self.controller!r}")
        if not (isinstance(self.camera_motion_every, int) and self.camera_motion_every >= 0):
            raise InputError(f"camera_motion_every must be a whole number of frames >= 0, not {self.camera_motion_every!r}")
        n = self.average_still_frames
        if isinstance(n, bool) or not isinstance(n, int) or not (0 <= n <= 30):
            raise InputError(f"average_still_frames must be a whole number of frames from 0 (off) to 30, not {n!r}")
        if not (self.max_predicted_tre_mm > 0):
            raise InputError("max_predicted_tre_mm must be a positive number of mm")
        c = self.tre_confidence
        if isinstance(c, bool) or not isinstance(c, (int, float)) or not (c == 0 or 0.5 <= float(c) <= 0.999):
            raise InputError(f"tre_confidence must be 0 (off) or a probability from 0.5 to 0.999 (e.g. 0.95), not {c!r}")
        from monotracker.engine.plan.checks import check_ball_finish

        why = check_ball_finish(self.ball_finish)
        if why:
            raise InputError(why)
        if self.camera_adapt:
            kind = str(self.camera_adapt).partition(":")[0]
            if kind not in ("bin", "scale", "crop"):
                raise InputError(f"camera_adapt {self.camera_adapt!r} not understood: use bin:N, scale:F or crop:X,Y,W,H")
        if self.camera_optics is not None:
            from monotracker.sim.optics import PRESETS

            if self.camera_optics not in PRESETS:
                raise InputError(f"camera_optics must be one of {', '.join(sorted(PRESETS))} (or unset for the "
                                 f"simple render), not {self.camera_optics!r}")
            if self.camera != "sim":
                raise InputError(f"camera_optics applies to the rendered simulated camera (camera='sim') only, "
                                 f"not camera={self.camera!r}")
        if not isinstance(self.freeze_heap, bool):
            raise InputError(f"freeze_heap must be True or False, not {self.freeze_heap!r}")
        c = self.compute_charge_s
        if c is not None:
            if isinstance(c, bool) or not isinstance(c, (int, float)) or not (0.0 <= float(c) <= 10.0):
                raise InputError(f"compute_charge_s must be a number of seconds from 0 to 10 (or unset for the "
                                 f"measured CPU time), not {c!r}")
            if self.clock != "sim":
                raise InputError("compute_charge_s applies to clock='sim' only (the real clock charges the real time)")
        from monotracker.engine.pipeline_priority import pose_priority_problem

        why = pose_priority_problem(self.pose_nice, self.pose_rt_priority)
        if why:
            raise InputError(why)
        if self.resume_dwell_s < 0 or self.start_wait_s < 0:
            raise InputError("resume_dwell_s and start_wait_s must be >= 0 s")
        if not str(self.arm_pin):
            raise InputError("arm_pin must not be empty")
        t = self.ct_job_timeout_s
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not (1.0 <= float(t) <= 86400.0):
            raise InputError(f"ct_job_timeout_s must be a number of seconds from 1 to 86400, not {t!r}")
