"""One surgical session: the engine that the web app and the headless demo both drive.

Public API (the engine <-> UI contract)::

    from monotracker.engine import Session, SessionConfig

    cfg = SessionConfig(home=Path(...),        # plan.json, audit.sqlite, logs (default paths.data_dir())
                        camera="sim",            # "sim" | "sim-points" | "device:0" | "file:/path/video.mp4" | "folder:/path"
                        trajectory="breathing",  # simulated head motion: still|drift|breathing|jumps (sim only)
                        robot="sim",             # "sim" | "ur:192.168.1.10"
                        arm_pin="1234",          # operator PIN checked by arm(pin)
                        clock="real")            # "real": engine threads + wall clock (web app)
                                                 # "sim": no threads, a driver calls s.advance(dt) (demo/tests)
    s = Session(cfg)      # restores the saved plan if any; ALWAYS starts disarmed
    s.start()             # starts the worker threads (clock="real"); s.shutdown() stops everything safely
    s.advance(dt)         # clock="sim" only: run camera, registration and control for dt seconds

Every command returns at once with a :class:`CommandResult` ``(ok, message)``; heavy work runs
on engine threads. Commands never raise for operator mistakes (the message says what is wrong)::

    s.load_ct(path)                     # async job: load + detect fiducials + head surface; progress in snap.job
    s.load_sample_ct()
    s.set_fiducial_kit(radius_mm, density_hu=None)   # kept in the plan; with a CT: detection again (CT job)
    s.cancel_ct_job()                   # stop the CT job; previous CT and plan stay (also: config.ct_job_timeout_s)
    s.set_fiducial_status(fid_id, "confirmed" | "rejected" | "detected")
    s.add_fiducial(p_lps_mm, radius_mm=None, manual=False)   # operator-added fiducial (LPS mm); status "added";
                                        #   with a CT it must be a dense ball there, else refused (manual=True: unverified)
    s.set_fiducial_role(fid_id, "registration" | "validation")   # validation: kept out of the fit,
                                        # verifies it (snap.pose.validation_tre_mm; arming gated)
    s.confirm_fiducials()               # locks the fiducial set (needs >= 4 confirmed/added)
    s.unlock_fiducials()                # back to editing (refused while armed/tracking)
    s.set_entry(p_lps_mm); s.set_target(p_lps_mm)   # planning; needs locked fiducials
    s.use_sample_plan()                 # phantom sample entry/target (sample CT)
    s.new_plan()                        # forget everything (refused while armed)
    s.set_camera(source, calibration_path=None)
    s.start_camera(); s.stop_camera()   # pose stream on its own thread
    s.set_hand_eye(T_base_cam_mm)       # 4x4 mm; the sim camera sets it from the OR layout
    s.plan_not_ready() -> str | None    # why arming/tracking is refused (plan_checks, CT loaded, re-confirmation)
    s.reconfirm_plan()                  # the operator re-confirms after an integrity alarm (edited outside, CT/calibration changed)
    s.integrity_alarms() -> [(code, line)]   # integrity conditions that stand until they clear (for snap.alarms)
    s.arm(pin); s.disarm()               # arm needs a fresh trusted pose for this plan; wrong PINs: 5 tries, then a 30 s lockout (doubling), see engine/control.py
    s.claim_control(client_id, pin, label=""); s.release_control(client_id)   # one browser client in control
    s.for_client(client_id) -> ClientSession    # reads as is; commands only while in control; estop() always
    s.start_tracking(); s.stop_tracking()   # needs armed + plan + trusted fresh pose + hand-eye
    s.estop(); s.reset_estop()          # e-stop is latched; reset leaves the arm disarmed; estop() waits
                                        #   (~1 s at most) for the robot controller's acknowledgement
    s.request_estop()                   # the stop channel alone: never blocks (a web server's event loop)
    s.inject_fault(name)                # sim only: "camera-freeze"|"occlude-all"|"robot-disconnect"|"bad-pose"|"none"
    s.export_slicer_markups(folder) -> list[Path]   # .mrk.json, LPS
    s.start_recording(folder); s.stop_recording()   # frames + detections + poses + robot + alerts
                                        # to a folder (docs/interop.md); state in snap.recording

    snap = s.snapshot()   # immutable copy (monotracker.engine.snapshot.Snapshot), cheap at 30 Hz
    snap.step             # "ct" | "plan" | "register" | "robot": the workflow step the session is at
    snap.job              # None or Job(name, progress 0..1, message, error, done)
    snap.ct               # None or CTSummary(path, shape, spacing_mm, notes, rejected, detection); snap.head_mesh: HeadMesh(vertices LPS mm, faces)
    snap.fiducials        # tuple of Fiducial(id, centre_lps_mm, radius_mm, score, status)
    snap.fiducials_locked # bool
    snap.plan             # PlanSummary(entry_lps_mm, target_lps_mm, path_length_mm,
                          #             angle_to_skin_normal_deg, distance_to_fiducials_mm, complete)
    snap.camera           # CameraSummary(source, running, fps, K, dist, image_size, calibration_path, error, frames)
    snap.pose             # None or PoseSummary(t, age_s, ok, trusted, reason, T_cam_ct, n_visible,
                          #   fiducial_status, residuals_px, fre_mm, predicted_tre_mm, latency_ms, truth_tre_mm,
                          #   stale): None again after the plan's fiducials/path/CT change or the camera stops;
                          #   trusted=False, stale=True while the engine holds for a stale stream
    snap.robot            # RobotSummary(state "disarmed"|"armed"|"tracking"|"holding"|"estopped", q rad,
                          #   tip_error_mm, angle_error_deg, speed_mm_s, connected, message, latency_ms)
    snap.scene            # SceneGeometry(T_base_cam, T_cam_ct, T_base_ct, T_base_tip, T_base_target, q), mm
    snap.control          # ControlSummary(controller client id or None, controller_label, since, pin_locked_s)
    snap.alarms           # active conditions, most important first: Alarm(code, level, priority, message, since, count)
    snap.recording        # None or RecordingSummary(path, frames, running, dropped, error)
    snap.alerts           # recent alerts (Event: t, t_session, kind, level "info"|"warning"|"alarm", code, message, data)
    s.volume()            # the loaded CT Volume (LPS mm) for read-only display, or None
    s.latest_frame()      # (image BGR uint8, frame_index, estimate) for the overlay, or None; estimate is
                          #   vision's PoseEstimate (image_points_px per fiducial, status, residuals) for
                          #   "sim" and real cameras, the engine's PoseSample for "sim-points"
    s.subscribe(callback) # callback(Event) on every alert/event (engine thread); returns unsubscribe()
    s.audit_entries(limit=None) -> list[AuditEntry]

Alert codes (``Event.kind == "alert"``; level in brackets) the UI can rely on:
``occlusion`` [warning] fewer than ``min_fiducials`` matched, arm holds; ``pose_jump`` [warning] the
pose disagrees with the last trusted one (a wrong pose or a real jump; followed after
``confirm_frames`` consistent frames), arm holds; ``bad_pose`` [warning] FRE too large; ``pose_lost``
[warning] the estimator failed; ``pose_stale`` [warning] freshest trusted pose older than
``max_pose_age_s``; ``camera_freeze`` [alarm] no new frame for ``freeze_after_s``; ``resumed`` [info]
the pose is trusted again (tracking resumes by itself); ``fiducials_lost`` / ``fiducials_back``
[info] fiducials left / re-entered the camera's view (with how many remain); ``camera_stopped``
[warning]; ``engine_error`` [alarm] an internal error in the engine loop (arm held);
``robot_disconnected`` [alarm] /
``robot_connected`` [info]; real cameras: ``camera_ended`` [warning] the video/folder ended,
``frame_unreadable`` [warning] a corrupt frame (skipped), ``camera_disconnected`` [alarm],
``camera_uncalibrated`` / ``camera_compressed`` / ``colour_clash`` [warning] nominal
intrinsics / lossy frames (MJPEG, JPEG files, a lossy video codec) / a large area of the balls'
colour (learn the colour), shown while that camera runs (the last while the area is seen),
``frame_size`` [warning] frame size differs from the calibration, ``frame_grayscale`` [alarm] the
frames are grayscale (a monochrome camera or grayscale files: no ball can be found); poses: ``tre_limit``
[warning] predicted error at the target over ``max_predicted_tre_mm``, ``weak_geometry`` /
``pose_implausible`` [warning], ``fiducial_moved`` [warning] a ball moved since the CT (named,
with its shift in mm; excluded from then on); ``robot_warning`` [warning] from the robot's safety layer; integrity
(engine/plan_commands.py, engine/audit.py): ``plan_field_rejected`` / ``plan_changed_outside`` /
``plan_reconfirm_pending`` / ``plan_ct_changed`` / ``plan_ct_missing`` / ``calibration_changed`` /
``plan_path_invalid`` / ``home_unwritable`` / ``audit_unavailable`` / ``audit_delayed`` / ``audit_lost``
[alarm], ``home_writable`` / ``audit_recovered`` [info], ``fiducial_unverified`` [warning]; ``estop``
[alarm]; ``estop_unconfirmed`` [alarm] STOP signalled but the robot controller did not confirm it;
``session_unlocked`` [warning] the session folder could not be locked (read-only); ``pin_lockout`` [alarm] too many wrong PIN tries, arming and taking control locked (each
wrong try is an ``arm_refused`` / ``control_refused`` *event*, never an alert, never the PIN); ``camera_failed`` / ``ct_failed`` / ``plan_save_failed``
/ ``plan_unreadable`` [alarm]; ``fiducials_detection`` / ``head_sphere`` [warning]. Decisions and
state changes are ``kind == "event"`` (``fiducial_confirmed``, ``fiducials_locked``, ``entry_set``,
``arm``, ``tracking_started``, ``robot_state`` (one per robot transition, in order, with its own
reason), ``session_lock_recovered`` (this session took over the folder lock of a process that was
killed), ``fault_injected``, ...); all of them are in the audit log.

One session per folder: the session locks its ``home`` (``engine/session_lock.py``); a second
session on it raises :class:`~monotracker.engine.session_lock.SessionFolderBusy` naming the holder.

Camera sources (``engine/vision_rig.py``): ``"sim"`` the rendered digital-twin camera (vision's
SimulatedCamera + classical detector + PoseTracker), ``"sim-points"`` the twin at the level of
detected points (no rendering), ``"device:N" | "file:PATH" | "folder:PATH"`` real sources through
vision's PoseStream (clock="real"; pass the calibration file to ``set_camera``). Per-fiducial
statuses in ``snap.pose.fiducial_status`` use vision's words: ``"seen" | "newly_lost" |
"occluded" | "unknown"``, keyed by fiducial id.

Threading: every public method may be called from any thread (viser callbacks). State lives
behind one re-entrant lock; methods hold it only for bookkeeping and for the plan's atomic save
(a few ms: a command saves the new plan first and swaps it in only once it is on disk, so the file
and the in-memory plan never disagree), never across CT loading, registration or robot motion.
The audit log is written by its own thread from a bounded queue: no command waits on it.
Snapshots are copies with read-only arrays.

Validation: one check per kind of plan state (``engine/plan_checks.py``), used by the commands,
by the field-by-field restore of ``plan.json`` and by the arming gate: what a setter refuses, a
restore refuses too; nothing is armed without a complete plan that passes every check.

Safety choices: the session always starts disarmed, also after a crash; arming needs the PIN;
tracking needs a trusted pose (>= ``min_fiducials`` visible, FRE below ``max_fre_mm``, passes the
jump gate) younger than ``max_pose_age_s``; anything else makes the tracker hold (the arm stands
still in place) and raises an alert; tracking resumes by itself when the pose is trusted again
(hold is not a stop: the operator's ``stop_tracking``/``disarm``/``estop`` are). Every decision
and alert goes to the append-only audit log.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from pathlib import Path

import numpy as np

from monotracker.engine.alarms import CATALOGUE, DERIVED_CODES, AlarmBoard, level_of
from monotracker.engine.audit import AuditEntry, AuditLog
from monotracker.engine.control_commands import ControlCommands
from monotracker.engine.ct_commands import CTCommands
from monotracker.engine.rig_commands import RigCommands
from monotracker.engine.config import SessionConfig
from monotracker.engine.control import ControlArbiter, PinGuard
from monotracker.engine.events import Event, EventBus
from monotracker.engine import plan_checks
from monotracker.engine.plan_commands import PlanCommands, _fail, _home_write_problem, _ok, _prepare_home
from monotracker.engine.plan import (
    Plan,
    angle_to_skin_normal_deg,
    distance_segment_to_points_mm,
    path_length_mm,
)
from monotracker.engine.session_lock import SessionFolderLock
from monotracker.engine.snapshot import (
    CommandResult,
    CTSummary,
    Fiducial,
    HeadMesh,
    Job,
    PlanSummary,
    Snapshot,
    frozen_array,
)
from monotracker.errors import MonoTrackerError

log = logging.getLogger(__name__)

PLAN_FILE = "plan.json"
AUDIT_FILE = "audit.sqlite"


class SimClock:
    """A settable clock (s) for clock="sim" sessions."""

    def __init__(self, t0: float = 0.0):
        self._t = float(t0)
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            return self._t

    def set(self, t: float) -> None:
        """Set the simulated time, s."""
        with self._lock:
            self._t = float(t)


class Session(PlanCommands, CTCommands, ControlCommands, RigCommands):
    """One surgical session (see the module docstring for the whole API)."""

    def __init__(self, config: SessionConfig | None = None, *, camera_factory=None, robot_factory=None):
        """``camera_factory(source, calibration_path, plan, cfg, session) -> CameraRig`` and
        ``robot_factory(cfg, session) -> RobotRig`` replace the default vision/robot wiring
        (``monotracker.engine.components``), e.g. for tests on doubles."""
        from monotracker.paths import data_dir

        self.camera_factory = camera_factory
        self.robot_factory = robot_factory
        self.config = config or SessionConfig()
        self.config.validate()
        self.home = Path(self.config.home) if self.config.home is not None else data_dir()
        _prepare_home(self.home)
        # one session per folder: a second one is refused naming the holder (engine/session_lock.py)
        self._folder_lock = SessionFolderLock(self.home).acquire()
        self.session_id = uuid.uuid4().hex[:12]
        self.clock = SimClock() if self.config.clock == "sim" else time.monotonic
        self._lock = threading.RLock()
        self._plan_path = self.home / PLAN_FILE
        self._audit = AuditLog(self.home / AUDIT_FILE, self.session_id,
                               on_problem=lambda level, code, msg, data: self._bus.alert(level, code, msg, data))
        self._bus = EventBus(sink=self._audit.record_event, clock=self.clock, alert_level=level_of)
        self._job: Job | None = None
        self._job_thread: threading.Thread | None = None
        self._ct: CTSummary | None = None
        self._volume = None
        self._head_mesh: HeadMesh | None = None
        self._head_normals: np.ndarray | None = None
        self._anatomy: plan_checks.Anatomy | None = None  # what the CT tells the plan checks
        self._ct_sha256: str | None = None  # content hash of the loaded CT
        self._reconfirm: list[str] = []  # why the operator must re-confirm the plan before arming
        self._home_unwritable: str | None = None  # last save failure while the home is unwritable
        self._started = False
        self._closed = False
        self._recorder = None  # interop.recording.SessionRecorder while/after recording
        self._plan = Plan()
        self._pin_guard = PinGuard(self.config.arm_pin)
        self._alarm_board = AlarmBoard()  # active conditions (snap.alarms); the loop sets and clears them
        self._control = ControlArbiter()
        unwritable = _home_write_problem(self.home)
        if unwritable:
            self._home_unwritable = unwritable
            self._bus.alert("alarm", "home_unwritable", f"cannot write the session folder {self.home}: {unwritable}; "
                            "the plan cannot be changed and the audit log goes to a spill file until it is writable")
        key = self._audit.key  # this machine's integrity key (engine/integrity.py), outside the home
        if key is not None and key.problem:
            self._bus.alert("warning", "integrity_key_unavailable", f"{key.problem}: the audit log is protected by "
                            "its hash chain alone (no MAC, no anchor)")
        if self._audit.tampered:
            self._bus.alert("alarm", "audit_tampered", f"audit log {self._audit.path}: {self._audit.tampered} "
                            "(recorded in the log; `monotracker audit verify` names it)")
        if self._audit.open_error:
            self._bus.alert("alarm", "audit_unavailable", f"audit database {self._audit.path} cannot be opened "
                            f"({self._audit.open_error}); events go to {self._audit.spill_path}")
        self._restore_plan()
        ct_path = self._plan.ct_path
        if ct_path and not Path(ct_path).exists():
            self._bus.alert("alarm", "plan_ct_missing", f"the plan's CT {ct_path} is missing; the plan cannot be "
                            "checked or armed until it is back (or start a new plan)", {"path": ct_path})
        # camera + loop + robot wiring (monotracker.engine.loop); created lazily
        from monotracker.engine.loop import TrackingLoop

        self._loop = TrackingLoop(self)
        self._bus.event("session_started", f"session {self.session_id} started, disarmed",
                        {"home": str(self.home), "camera": self.config.camera, "robot": self.config.robot,
                         "clock": self.config.clock, "plan_revision": self._plan.revision})
        self._note_folder_lock()

    # ================================================================== lifecycle
    def start(self) -> CommandResult:
        """Start the engine threads (event dispatcher; camera/control threads when running)."""
        with self._lock:
            if self._closed:
                return _fail("session is shut down")
            if self._started:
                return _ok("already started")
            self._started = True
        self._bus.start()
        self._loop.start_threads()
        # After a restart the plan is back but the CT volume and surface are not: reload them in
        # the background for the views (the saved fiducials are kept, see load_ct).
        with self._lock:
            ct_path = self._plan.ct_path if self._ct is None else None
        if ct_path and Path(ct_path).exists():
            self.load_ct(ct_path)
        return _ok("started")

    def shutdown(self) -> None:
        """Stop tracking, disarm, stop every thread, close the audit log. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        try:
            self._loop.shutdown()
            self.stop_recording()
        finally:
            self._bus.event("session_shutdown", "session shut down")
            self._bus.stop()
            self._audit.close()
            self._folder_lock.release()

    def _note_folder_lock(self) -> None:
        """The audit log says when this session took over a lock its holder never released (it
        was killed or crashed), and when the folder could not be locked at all."""
        lock = self._folder_lock
        if lock.took_over:
            h = lock.took_over
            self._bus.event("session_lock_recovered", f"session folder lock taken over from MonoTracker pid "
                            f"{h.get('pid', '?')} on host {h.get('host', '?')} (since {h.get('since_iso', '?')}), "
                            "which ended without releasing it (killed or crashed)", {"previous": h}, level="warning")
        if lock.note:
            self._bus.alert("warning", "session_unlocked", f"{lock.note}: another server could use {self.home} "
                            "at the same time")

    def __enter__(self) -> "Session":
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()

    def advance(self, dt: float) -> None:
        """clock="sim" only: run camera, registration and control in lock-step for ``dt`` s."""
        if self.config.clock != "sim":
            raise MonoTrackerError("advance() is only for clock='sim' sessions")
        self._loop.advance(float(dt))

    # ================================================================== events
    def subscribe(self, callback) -> "callable":
        """``callback(event)`` for every later event/alert; returns the unsubscribe function."""
        return self._bus.subscribe(callback)

    def alert(self, level: str, code: str, message: str, data: dict | None = None) -> Event | None:
        """Raise an alert (to subscribers and the audit log). Used by the engine's parts.

        ``level`` counts only for a code without a catalogue row (:data:`~.alarms.CATALOGUE`):
        a catalogued code carries its row's level. Warnings from the robot's safety layer
        (``pulse`` rows) and the camera's setup (uncalibrated, lossy frames: ``camera_setup``
        rows) are also active conditions in ``snap.alarms``; repeated robot warnings (a loaded
        machine overrunning the control period) are reported at most once per quiet time
        (returns None when held back)."""
        on_board = "loop_overrun" if code == "robot_warning" and "overran" in message else code
        kind = CATALOGUE.get(on_board)
        if kind is not None and kind.pulse:
            now = float(self.clock())
            report = self._alarm_board.set(on_board, message, now)
            self._alarm_board.clear(on_board, now)  # a pulse: shown for its linger time
            if not report:
                log.info("%s (not re-reported): %s", code, message)
                return None
        elif kind is not None and kind.camera_setup:
            self._alarm_board.set(code, message, float(self.clock()))
        return self._bus.alert(level, code, message, data)

    def clear_condition(self, code: str) -> None:
        """A camera setup condition (:data:`~.alarms.CAMERA_SETUP_CODES`) raised with
        :meth:`alert` no longer holds (thread-safe)."""
        self._alarm_board.clear(code, float(self.clock()))

    def _persistent_alarm(self, code: str, message: str, data: dict | None = None) -> Event:
        """An alert that is also an active condition (``snap.alarms``) until it is cleared."""
        self._alarm_board.set(code, message, float(self.clock()))
        return self._bus.alert(level_of(code, "alarm"), code, message, data)

    def record(self, code: str, message: str, data: dict | None = None, level: str = "info") -> Event:
        """Record a decision/state change (to subscribers and the audit log)."""
        return self._bus.event(code, message, data, level)

    def audit_entries(self, limit: int | None = None, code: str | None = None) -> list[AuditEntry]:
        """Rows of the audit log (all sessions in this home), oldest first. Waits (at most 5 s)
        for the rows still queued; rows delayed to a spill file appear once copied back in."""
        return self._audit.entries(code=code, limit=limit)

    # ================================================================== plan persistence
    @property
    def plan_path(self) -> Path:
        """Where the plan is saved: ``plan.json`` in the session's ``home``."""
        return self._plan_path

    def plan_copy(self) -> Plan:
        """A deep copy of the current plan."""
        with self._lock:
            return self._plan.copy()

    def new_plan(self) -> CommandResult:
        """Forget CT, fiducials, path (calibrations are kept). Refused while armed."""
        if self._loop.robot_state() not in ("disarmed", "estopped"):
            return _fail("disarm the robot before starting a new plan")
        with self._lock:
            keep = self._plan
            integ = {k: v for k, v in keep.integrity.items() if k == "calibration_sha256"}
            plan = Plan(camera_source=keep.camera_source, calibration_path=keep.calibration_path,
                        K=keep.K, dist=keep.dist, image_size=keep.image_size, T_base_cam=keep.T_base_cam,
                        integrity=integ)
            err = self._commit_plan_locked(plan, "new plan")
            if err:
                return _fail(err)
            self._ct = None
            self._volume = None
            self._head_mesh = None
            self._head_normals = None
            self._anatomy = None
            self._reconfirm = []
        self._alarm_board.clear_all(("plan_field_rejected", "fiducial_moved"), float(self.clock()))
        self._bus.event("plan_cleared", "new plan: CT, fiducials and path cleared")
        self._loop.plan_changed("new plan", restart_camera=False)
        return _ok("new plan")

    def volume(self):
        """The loaded CT :class:`~monotracker.ct.Volume` (LPS mm) for read-only display (slice
        views), or None while no CT is loaded. Never modify it: the engine owns it."""
        with self._lock:
            return self._volume

    # ================================================================== snapshot
    def _plan_summary(self, plan: Plan) -> PlanSummary:
        e, t = plan.entry_lps_mm, plan.target_lps_mm
        if e is None or t is None:
            return PlanSummary(frozen_array(e), frozen_array(t), None, None, None, False)
        ang = None
        if self._head_mesh is not None and self._head_normals is not None:
            ang = angle_to_skin_normal_deg(e, t, self._head_mesh.vertices, self._head_normals)
        return PlanSummary(frozen_array(e), frozen_array(t), path_length_mm(e, t), ang,
                           distance_segment_to_points_mm(e, t, plan.fiducial_centres()), True)

    def snapshot(self) -> Snapshot:
        """An immutable, consistent copy of the session state (thread-safe, cheap)."""
        with self._lock:
            plan = self._plan
            fids = tuple(Fiducial(f.id, frozen_array(f.centre_lps_mm), f.radius_mm, f.score, f.status, f.role)
                         for f in plan.fiducials)
            plan_summary = self._plan_summary(plan)
            job, ct, mesh, locked = self._job, self._ct, self._head_mesh, plan.fiducials_locked
            if not locked:
                step = "ct"
            elif not plan.path_complete:
                step = "plan"
            else:
                step = None
        camera, pose, robot, scene = self._loop.summaries()
        if step is None:
            step = "robot" if (robot.state != "disarmed" or (pose is not None and pose.trusted)) else "register"
        return Snapshot(
            t=float(self.clock()), step=step, job=job, ct=ct, head_mesh=mesh, fiducials=fids,
            fiducials_locked=locked, plan=plan_summary, camera=camera, pose=pose, robot=robot, scene=scene,
            alerts=tuple(self._bus.recent("alert")[-50:]), plan_path=str(self._plan_path),
            audit_path=str(self._audit.path), control=self.control_summary(),
            alarms=self._active_alarms(),
            recording=self._recording_summary(),
        )

    def _active_alarms(self):
        """The board's active conditions, with the conditions derived from the state (``derived`` rows)."""
        now, board = float(self.clock()), self._alarm_board
        standing = dict(self.integrity_alarms())
        for code in DERIVED_CODES:
            if code in standing:
                board.set(code, standing[code], now)
            else:
                board.clear(code, now)
        return board.active(now)
