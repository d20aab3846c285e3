"""Immutable state snapshots the engine hands to the UI and the demo (see ``session.py``).

Every array inside a snapshot is a private, read-only copy: a snapshot can be read from any thread
while the engine keeps running. Units: CT/camera/plan side in millimetres, LPS for CT points,
pixels for images, joint angles in radians. Transforms are 4x4 ``T_to_from``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monotracker.engine.events import Event


def frozen_array(a, dtype=float) -> np.ndarray | None:
    """A read-only copy of ``a`` (or None)."""
    if a is None:
        return None
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


@dataclass(frozen=True)
class CommandResult:
    """What a command returns at once: ``ok`` and a one-line ``message`` for the operator."""

    ok: bool
    message: str = ""

    def __bool__(self) -> bool:  # `if s.arm(pin): ...`
        return self.ok

    @classmethod
    def done(cls, message: str = "") -> "CommandResult":
        """The command did what was asked (``ok`` True)."""
        return cls(True, message)

    @classmethod
    def refused(cls, message: str) -> "CommandResult":
        """The command changed nothing; ``message`` says why in one line (``ok`` False)."""
        return cls(False, message)


@dataclass(frozen=True)
class Job:
    """A background job (CT loading). ``progress`` 0..1; ``error`` is a one-line message or None."""

    name: str
    progress: float
    message: str
    error: str | None = None
    done: bool = False


@dataclass(frozen=True)
class CTRejectedBlob:
    """A dense blob the fiducial detection did not take: ``centre_lps_mm`` (3,) LPS mm,
    ``radius_mm`` (fitted, or of a ball of the blob's volume; mm), ``n_voxels``, ``reason``."""

    centre_lps_mm: tuple
    radius_mm: float
    n_voxels: int
    reason: str


@dataclass(frozen=True)
class CTSummary:
    """The loaded CT: ``path``, ``shape`` (z, y, x voxels), ``spacing_mm`` (x, y, z), ``notes``;
    ``rejected``: the dense blobs the last detection did not take (:class:`CTRejectedBlob`);
    ``detection``: its one-line outcome."""

    path: str
    shape: tuple
    spacing_mm: tuple
    notes: tuple = ()
    rejected: tuple = ()
    detection: str = ""


@dataclass(frozen=True)
class HeadMesh:
    """Skin surface for the 3D view: ``vertices`` (n, 3) LPS mm, ``faces`` (m, 3) int."""

    vertices: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True)
class Fiducial:
    """One CT fiducial. ``status``: ``"detected" | "confirmed" | "rejected" | "added"``.

    ``"added"`` fiducials (operator clicks) count as confirmed. ``centre_lps_mm`` (3,) LPS mm.
    """

    id: int
    centre_lps_mm: np.ndarray
    radius_mm: float
    score: float
    status: str
    #: "registration" (used in the fit) or "validation" (kept out of the fit to verify it)
    role: str = "registration"


@dataclass(frozen=True)
class PlanSummary:
    """The planned path. Points LPS mm (None until set). ``angle_to_skin_normal_deg``: angle
    between the path (entry -> target) reversed and the outward skin normal at the entry (0 =
    perpendicular to the skin; None without a head surface). ``distance_to_fiducials_mm``: the
    smallest distance from the path segment to a confirmed fiducial centre."""

    entry_lps_mm: np.ndarray | None
    target_lps_mm: np.ndarray | None
    path_length_mm: float | None
    angle_to_skin_normal_deg: float | None
    distance_to_fiducials_mm: float | None
    complete: bool


@dataclass(frozen=True)
class CameraSummary:
    """Camera state. ``K`` 3x3 px, ``dist`` OpenCV distortion, ``image_size`` (w, h) px,
    ``fps`` achieved frames per second, ``error`` one line or None."""

    source: str
    running: bool
    fps: float
    K: np.ndarray | None
    dist: np.ndarray | None
    image_size: tuple | None
    calibration_path: str | None
    error: str | None
    frames: int = 0


@dataclass(frozen=True)
class PoseSummary:
    """The latest pose estimate. ``t`` capture time (session clock, s); ``age_s`` now - t;
    ``T_cam_ct`` 4x4 mm or None; ``fiducial_status`` dict id -> "seen"|"newly_lost"|"occluded"|"unknown";
    ``residuals_px`` dict id -> px; ``fre_mm``, ``predicted_tre_mm`` at the planned target;
    ``latency_ms`` capture -> estimate; ``trusted``: the engine's verdict (ok, >= 4 fiducials,
    passes the plausibility gates) that decides tracking vs holding; ``reason`` one line."""

    t: float
    age_s: float
    ok: bool
    trusted: bool
    reason: str
    T_cam_ct: np.ndarray | None
    n_visible: int
    fiducial_status: dict
    residuals_px: dict
    fre_mm: float | None
    predicted_tre_mm: float | None
    latency_ms: float | None
    truth_tre_mm: float | None = None  # simulator only: TRE at the planned target vs truth
    #: why the pose is not trusted, as an alert code ("" when trusted; e.g. "tre_limit", "frame_size")
    code: str = ""
    #: the trust limit on ``predicted_tre_mm`` (mm)
    max_predicted_tre_mm: float | None = None
    # accuracy verification (engine/verification.py): validation fiducial id -> error (mm, point to
    # viewing ray) or None (not seen); ``validation_ok`` None when the plan has no validation fiducials
    validation_tre_mm: dict = field(default_factory=dict)
    validation_ok: bool | None = None
    validation_reason: str = ""
    stale: bool = False  # the engine holds because the pose stream is not fresh (then trusted is False)
    #: capture time (session clock, s) of the newest trusted estimate, None since the pose was
    #: last cleared: what "stale since" means for every figure derived from the pose
    trusted_t: float | None = None
    #: frames of a still view whose mean the detector read for this pose (1 = the frame alone;
    #: the opt-in still-view mean, ``SessionConfig.average_still_frames``)
    averaged_frames: int = 1
    #: fiducials found but left out of this pose because the other balls put them more than a
    #: pixel or two away (partly hidden, a reflection): id -> px from where the others put it
    set_aside: dict = field(default_factory=dict)


@dataclass(frozen=True)
class RobotSummary:
    """Robot state. ``state``: ``"disarmed" | "armed" | "tracking" | "holding" | "estopped"``.
    ``q`` (6,) rad; ``tip_error_mm`` needle tip to planned entry; ``angle_error_deg`` needle axis
    to planned path; ``speed_mm_s`` tip speed; ``connected``; ``message`` one line."""

    state: str
    q: np.ndarray | None
    tip_error_mm: float | None
    angle_error_deg: float | None
    speed_mm_s: float
    connected: bool
    message: str
    latency_ms: float | None = None  # frame capture -> robot command, last command
    #: link up but the arm's control program stopped ("watchdog" | "pendant" | "paused" |
    #: "protective_stop" | "emergency_stop" | "safeguard_stop" | "not_running"; "" while it
    #: runs); ``message`` says why; the operator's e-stop reset restarts it
    program_fault: str = ""
    #: where the control loop runs ("in-process thread" | "process pid N, SCHED_FIFO 10" ...)
    control: str = ""
    #: capture time (session clock, s) of the trusted pose ``tip_error_mm`` / ``angle_error_deg``
    #: were computed from (None when they are None): their age is ``snap.t - errors_t``
    errors_t: float | None = None
    #: session time (s) of the command ``latency_ms`` was measured on (None before the first)
    command_t: float | None = None


@dataclass(frozen=True)
class SceneGeometry:
    """Everything to place head, camera, path and robot in one frame (robot base, mm).

    ``T_base_cam`` hand-eye (mm); ``T_cam_ct`` latest trusted pose (mm); ``T_base_ct`` their
    product; ``T_base_tip`` current needle tip pose (z axis = needle direction, mm);
    ``T_base_target`` the commanded needle pose; ``q`` UR10 joints (rad). Any may be None.
    """

    T_base_cam: np.ndarray | None
    T_cam_ct: np.ndarray | None
    T_base_ct: np.ndarray | None
    T_base_tip: np.ndarray | None
    T_base_target: np.ndarray | None
    q: np.ndarray | None


@dataclass(frozen=True)
class ControlSummary:
    """Which browser client is in control (see ``engine/access.py``).

    ``controller``: the client id in control, None when nobody is (the local operator calling the
    Session directly is never refused). ``controller_label``: its display name. ``since``: session
    clock (s) when it took control. ``pin_locked_s``: seconds the PIN stays locked after too many
    wrong tries (0 when not locked)."""

    controller: str | None = None
    controller_label: str = ""
    since: float | None = None
    pin_locked_s: float = 0.0


@dataclass(frozen=True)
class Alarm:
    """One active condition (see ``engine/alarms.py``), shown until it clears.

    ``code`` stable name (e.g. ``"estop"``, ``"occlusion"``, ``"pin_lockout"``); ``level``
    ``"alarm" | "warning" | "info"``; ``priority`` 0 = most important; ``message`` one line;
    ``since`` session clock (s) when the condition began; ``count`` how many times it began
    (episodes) since the session started; ``remedy`` what the team can do, one line ("" when
    the message says it)."""

    code: str
    level: str
    priority: int
    message: str
    since: float
    count: int = 1
    remedy: str = ""


@dataclass(frozen=True)
class RecordingSummary:
    """Session recording (``Session.start_recording``): ``path`` the folder, ``frames`` written or
    queued, ``running``, ``dropped`` frames lost (real clock, disk too slow), ``error`` one line."""

    path: str
    frames: int
    running: bool
    dropped: int = 0
    error: str | None = None


@dataclass(frozen=True)
class LayoutError:
    """Predicted error at the planned target (mm) with ``n_balls`` balls seen: ``mean_mm`` and
    ``p95_mm`` of its length, ``rms_mm``; ``trusted`` the predicted share of frames the pose
    stream trusts (0..1). The registration's first-order model (``monotracker.planning``)."""

    n_balls: int
    mean_mm: float
    p95_mm: float
    rms_mm: float
    trusted: float


@dataclass(frozen=True)
class LayoutExpectation:
    """What a layout of balls gives from one camera placement: ``all_seen`` (every ball the
    camera sees) and ``worst_hidden`` (the one ball whose loss hurts most hidden too; its index
    ``worst_ball`` in that layout) as :class:`LayoutError`, None when they give no pose
    (``reason`` says why, one line); ``balls_seen`` of ``balls``; with the detector finding
    each seen ball with probability ``found_probability`` (``found_short`` for the
    ``short_of_skin`` seen balls with little skin around them): ``trusted_with_losses`` the expected
    share of trusted frames and ``pose_with_losses`` the chance of a pose at all (0..1; None
    when not predicted)."""

    balls: int
    balls_seen: int
    all_seen: LayoutError | None
    worst_hidden: LayoutError | None
    worst_ball: int | None
    reason: str = ""
    found_probability: float | None = None
    trusted_with_losses: float | None = None
    pose_with_losses: float | None = None
    found_short: float | None = None
    short_of_skin: int = 0

    @property
    def found_text(self) -> str:
        """How the outlook counted the balls found, in words ('' when not predicted)."""
        if self.found_probability is None:
            return ""
        from monotracker.planning.ball_losses import found_phrase

        return found_phrase(self.found_probability, self.found_short, self.short_of_skin)


@dataclass(frozen=True)
class LayoutSummary:
    """The fiducial-layout and camera-placement plan (``Session.plan_layout``; issue 31).

    ``job``: the planning job (progress 0..1, message, error one line, done); the fields below
    are those of the last plan that finished (None / empty until one has). Points LPS mm.

    ``balls_lps_mm`` (n, 3) suggested ball centres, numbered 1..n in this order;
    ``from_fiducial`` (n,) the plan fiducial id a suggested ball is (kept where it is), -1 for a
    new position; ``T_ct_cam`` the planned camera (4x4, camera -> CT mm: where it stands in the
    CT), ``camera_distance_mm`` to the point it aims at, ``K`` (3x3 px) and ``image_size`` (w, h
    px) of the camera model planned with (its field of view); ``suggestion`` the suggested
    balls from the planned camera; ``current`` the plan's registration fiducials from the planned
    camera, ``current_best`` from the best camera for them, :class:`LayoutExpectation` or None;
    ``balls_needed`` how many balls reach ``min_trusted`` trusted frames with one hidden when
    this count does not (None: it does, or not even the most the planner suggests would: see
    ``notes``); ``candidates_lps_mm`` (m, 3) the candidate ball positions on the skin and
    ``error_map_mm`` (m,) the predicted RMS error at the target with the worst ball hidden if
    one suggested ball moved there (NaN: not usable from the planned camera); ``target_lps_mm``,
    ``noise_px`` (image noise, px), ``radius_mm`` (ball radius) planned for; ``stale``: the CT,
    the fiducials or the path changed since (plan again), ``elapsed_s`` the planning time."""

    job: Job
    balls_lps_mm: np.ndarray | None = None
    from_fiducial: tuple = ()
    T_ct_cam: np.ndarray | None = None
    camera_distance_mm: float | None = None
    K: np.ndarray | None = None
    image_size: tuple | None = None
    suggestion: LayoutExpectation | None = None
    current: LayoutExpectation | None = None
    current_best: LayoutExpectation | None = None
    balls_needed: int | None = None
    min_trusted: float = 0.95
    notes: tuple = ()
    candidates_lps_mm: np.ndarray | None = None
    error_map_mm: np.ndarray | None = None
    target_lps_mm: np.ndarray | None = None
    noise_px: float | None = None
    radius_mm: float | None = None
    stale: bool = False
    elapsed_s: float | None = None

    @property
    def ready(self) -> bool:
        """A finished plan is there (it may be ``stale``)."""
        return self.balls_lps_mm is not None


@dataclass(frozen=True)
class Snapshot:
    """One consistent, immutable view of the session (see ``session.py`` for each field)."""

    t: float
    step: str
    job: Job | None
    ct: CTSummary | None
    head_mesh: HeadMesh | None
    fiducials: tuple
    fiducials_locked: bool
    plan: PlanSummary
    camera: CameraSummary
    pose: PoseSummary | None
    robot: RobotSummary
    scene: SceneGeometry
    alerts: tuple = field(default_factory=tuple)  # tuple[Event], newest last
    plan_path: str = ""
    audit_path: str = ""
    control: ControlSummary = field(default_factory=ControlSummary)
    alarms: tuple = field(default_factory=tuple)  # tuple[Alarm], most important first
    recording: RecordingSummary | None = None  # None when no recording was made in this session
    layout: LayoutSummary | None = None  # None until a layout was planned in this session (Plan step)
    #: the CT file or folder the plan was made on (None: no CT in the plan); with ``ct`` None
    #: after a restart, the CT the restored plan needs (``Session.load_ct`` on it restores it)
    plan_ct_path: str | None = None
    #: the balls' finish the plan states ("read", "matte", "glossy") or None (the launch
    #: setting, ``ball_finish_default``); the camera applies it (a running one restarts with it)
    ball_finish: str | None = None
    #: the session's launch setting of the balls' finish (``SessionConfig.ball_finish``)
    ball_finish_default: str = "read"

    @property
    def latest_alert(self) -> Event | None:
        return self.alerts[-1] if self.alerts else None
