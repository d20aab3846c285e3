"""One surgical session: the engine that the web app and the headless demo both drive.

Public API (the engine <-> UI contract; /work/wt/SESSION_API.md, refined here)::

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
    s.set_fiducial_status(fid_id, "confirmed" | "rejected" | "detected")
    s.add_fiducial(p_lps_mm, radius_mm=None)   # operator-added fiducial (LPS mm); status "added"
    s.confirm_fiducials()               # locks the fiducial set (needs >= 4 confirmed/added)
    s.unlock_fiducials()                # back to editing (refused while armed/tracking)
    s.set_entry(p_lps_mm); s.set_target(p_lps_mm)   # planning; needs locked fiducials
    s.use_sample_plan()                 # phantom sample entry/target (sample CT)
    s.new_plan()                        # forget everything (refused while armed)
    s.set_camera(source, calibration_path=None)
    s.start_camera(); s.stop_camera()   # pose stream on its own thread
    s.set_hand_eye(T_base_cam_mm)       # 4x4 mm; the sim camera sets it from the OR layout
    s.arm(pin); s.disarm()               # arm needs a fresh trusted pose for this plan; wrong PINs: 5 tries, then a 30 s lockout (doubling), see engine/control.py
    s.claim_control(client_id, pin, label=""); s.release_control(client_id)   # one browser client in control
    s.for_client(client_id) -> ClientSession    # reads as is; commands only while in control; estop() always
    s.start_tracking(); s.stop_tracking()   # needs armed + plan + trusted fresh pose + hand-eye
    s.estop(); s.reset_estop()          # e-stop is latched; reset leaves the arm disarmed
    s.inject_fault(name)                # sim only: "camera-freeze"|"occlude-all"|"robot-disconnect"|"bad-pose"|"none"
    s.export_slicer_markups(folder) -> list[Path]   # .mrk.json, LPS

    snap = s.snapshot()   # immutable copy (monotracker.engine.snapshot.Snapshot), cheap at 30 Hz
    snap.step             # "ct" | "plan" | "register" | "robot": the workflow step the session is at
    snap.job              # None or Job(name, progress 0..1, message, error, done)
    snap.ct               # None or CTSummary(path, shape, spacing_mm, notes); snap.head_mesh: HeadMesh(vertices LPS mm, faces)
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
``robot_connected`` [info]; ``robot_warning`` [warning] from the robot's safety layer; ``estop``
[alarm]; ``pin_lockout`` [alarm] too many wrong PIN tries, arming and taking control locked (each
wrong try is an ``arm_refused`` / ``control_refused`` *event*, never an alert, never the PIN); ``camera_failed`` / ``ct_failed`` / ``plan_save_failed``
/ ``plan_unreadable`` [alarm]; ``fiducials_detection`` / ``head_sphere`` [warning]. Decisions and
state changes are ``kind == "event"`` (``fiducial_confirmed``, ``fiducials_locked``, ``entry_set``,
``arm``, ``tracking_started``, ``robot_state``, ``fault_injected``, ...); all of them are in the audit log.

Camera sources (``engine/vision_rig.py``): ``"sim"`` the rendered digital-twin camera (vision's
SimulatedCamera + classical detector + PoseTracker), ``"sim-points"`` the twin at the level of
detected points (no rendering), ``"device:N" | "file:PATH" | "folder:PATH"`` real sources through
vision's PoseStream (clock="real"; pass the calibration file to ``set_camera``). Per-fiducial
statuses in ``snap.pose.fiducial_status`` use vision's words: ``"seen" | "newly_lost" |
"occluded" | "unknown"``, keyed by fiducial id.

Differences from SESSION_API.md (refinements, same shape): ``clock``/``advance`` for the
simulated-clock demo; ``unlock_fiducials``, ``new_plan``, ``use_sample_plan``, ``set_hand_eye``,
``inject_fault``, ``audit_entries``; ``snap.scene`` carries the geometry for the 3D views; alerts
are :class:`~monotracker.engine.events.Event` objects (with ``kind == "alert"``).

Threading: every public method may be called from any thread (viser callbacks). State lives
behind one re-entrant lock; methods hold it only for bookkeeping and for the plan's atomic save
(a few ms, so the file and the in-memory plan never disagree), never across CT loading,
registration or robot motion. Snapshots are copies with read-only arrays.

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

from monotracker.engine.alarms import AlarmBoard
from monotracker.engine.audit import AuditEntry, AuditLog
from monotracker.engine.config import FAULTS, SessionConfig
from monotracker.engine.control import ClientSession, ControlArbiter, PinGuard
from monotracker.engine.events import Event, EventBus
from monotracker.engine.plan import (
    Plan,
    PlanFiducial,
    angle_to_skin_normal_deg,
    distance_segment_to_points_mm,
    path_length_mm,
)
from monotracker.engine.snapshot import (
    CameraSummary,
    CommandResult,
    CTSummary,
    Fiducial,
    HeadMesh,
    Job,
    PlanSummary,
    PoseSummary,
    RobotSummary,
    SceneGeometry,
    Snapshot,
    frozen_array,
)
from monotracker.errors import InputError, MonoTrackerError

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
        with self._lock:
            self._t = float(t)


def _ok(msg: str = "") -> CommandResult:
    return CommandResult(True, msg)


def _fail(msg: str) -> CommandResult:
    return CommandResult(False, msg)


def _point3(p) -> np.ndarray:
    a = np.asarray(p, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError("a point needs three finite coordinates (LPS mm)")
    return a


class Session:
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
        self.home.mkdir(parents=True, exist_ok=True)
        self.session_id = uuid.uuid4().hex[:12]
        self.clock = SimClock() if self.config.clock == "sim" else time.monotonic
        self._lock = threading.RLock()
        self._plan_path = self.home / PLAN_FILE
        self._audit = AuditLog(self.home / AUDIT_FILE, self.session_id)
        self._bus = EventBus(sink=self._audit.record_event, clock=self.clock)
        self._job: Job | None = None
        self._job_thread: threading.Thread | None = None
        self._ct: CTSummary | None = None
        self._volume = None
        self._head_mesh: HeadMesh | None = None
        self._head_normals: np.ndarray | None = None
        self._started = False
        self._closed = False
        self._plan = Plan()
        self._pin_guard = PinGuard(self.config.arm_pin)
        self._alarm_board = AlarmBoard()  # active conditions (snap.alarms); the loop sets and clears them
        self._control = ControlArbiter()
        self._restore_plan()
        # camera + loop + robot wiring (monotracker.engine.loop); created lazily
        from monotracker.engine.loop import TrackingLoop

        self._loop = TrackingLoop(self)
        self._bus.event("session_started", f"session {self.session_id} started, disarmed",
                        {"home": str(self.home), "camera": self.config.camera, "robot": self.config.robot,
                         "clock": self.config.clock, "plan_revision": self._plan.revision})

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
        finally:
            self._bus.event("session_shutdown", "session shut down")
            self._bus.stop()
            self._audit.close()

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

        Warnings from the robot's safety layer and an uncalibrated camera are also active
        conditions in ``snap.alarms``; repeated robot warnings (a loaded machine overrunning the
        control period) are reported at most once per quiet time (returns None when held back)."""
        if code == "robot_warning":
            kind = "loop_overrun" if "overran" in message else "robot_warning"
            now = float(self.clock())
            report = self._alarm_board.set(kind, message, now)
            self._alarm_board.clear(kind, now)  # a pulse: shown for its linger time
            if not report:
                log.info("robot warning (not re-reported): %s", message)
                return None
        elif code == "camera_uncalibrated":
            self._alarm_board.set(code, message, float(self.clock()))
        return self._bus.alert(level, code, message, data)

    def record(self, code: str, message: str, data: dict | None = None, level: str = "info") -> Event:
        """Record a decision/state change (to subscribers and the audit log)."""
        return self._bus.event(code, message, data, level)

    def audit_entries(self, limit: int | None = None, code: str | None = None) -> list[AuditEntry]:
        """Rows of the audit log (all sessions in this home), oldest first."""
        return self._audit.entries(code=code, limit=limit)

    # ================================================================== plan persistence
    @property
    def plan_path(self) -> Path:
        return self._plan_path

    def _restore_plan(self) -> None:
        if not self._plan_path.exists():
            return
        try:
            plan = Plan.load(self._plan_path)
        except (OSError, ValueError) as exc:
            keep = self._plan_path.with_name(f"plan.unreadable-{int(time.time())}.json")
            try:
                self._plan_path.rename(keep)
            except OSError:
                keep = self._plan_path
            self._alarm_board.set("plan_unreadable", f"saved plan could not be read; kept as {keep.name}",
                                  float(self.clock()))
            self._bus.alert("alarm", "plan_unreadable",
                            f"saved plan could not be read ({exc}); kept as {keep.name}, starting empty")
            return
        self._plan = plan
        self._bus.event("plan_restored", f"plan restored (revision {plan.revision}, "
                        f"{len(plan.usable_fiducials())} fiducials, path {'set' if plan.path_complete else 'not set'})",
                        {"revision": plan.revision, "plan": plan.to_dict()})

    def _save_plan_locked(self, why: str) -> None:
        """Save the plan atomically; caller holds the lock. Raises MonoTrackerError on disk failure."""
        self._plan.revision += 1
        try:
            self._plan.save(self._plan_path)
        except OSError as exc:
            self._alarm_board.set("plan_save_failed", f"could not save the plan: {exc}", float(self.clock()))
            self._bus.alert("alarm", "plan_save_failed", f"could not save the plan: {exc}")
            raise MonoTrackerError(f"could not save the plan to {self._plan_path}: {exc}") from exc
        self._alarm_board.clear_all(("plan_save_failed", "plan_unreadable"), float(self.clock()))
        log.debug("plan saved (%s) revision %d", why, self._plan.revision)

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
            self._plan = Plan(camera_source=keep.camera_source, calibration_path=keep.calibration_path,
                              K=keep.K, dist=keep.dist, image_size=keep.image_size, T_base_cam=keep.T_base_cam,
                              revision=keep.revision)
            self._ct = None
            self._volume = None
            self._head_mesh = None
            self._head_normals = None
            self._save_plan_locked("new plan")
        self._bus.event("plan_cleared", "new plan: CT, fiducials and path cleared")
        self._loop.plan_changed("new plan", restart_camera=False)
        return _ok("new plan")

    # ================================================================== CT
    def load_sample_ct(self) -> CommandResult:
        from monotracker.paths import sample_ct_path

        return self.load_ct(sample_ct_path())

    def load_ct(self, path) -> CommandResult:
        """Start the CT job (load, detect fiducials, head surface). Progress in ``snap.job``.

        If the plan's fiducials are locked, the CT must be the one the plan was made on: its volume
        and surface are reloaded and the saved fiducials are kept (restart after a crash)."""
        path = str(path)
        with self._lock:
            if self._job is not None and not self._job.done:
                return _fail(f"busy: {self._job.name} is still running")
            if self._plan.fiducials_locked and self._plan.ct_path and Path(self._plan.ct_path) != Path(path):
                return _fail("the plan's fiducials are locked on another CT; start a new plan first")
            if not Path(path).exists():
                return _fail(f"no such file or folder: {path}")
            self._job = Job("load_ct", 0.0, f"loading {Path(path).name}")
            th = threading.Thread(target=self._ct_job, args=(path,), name="monotracker-ct", daemon=True)
            self._job_thread = th
        self._alarm_board.clear("ct_failed", float(self.clock()))
        self._bus.event("ct_load_started", f"loading CT {path}", {"path": path})
        th.start()
        return _ok("loading CT")

    def wait_for_job(self, timeout: float | None = None) -> Job | None:
        """Block until the current job ends (for scripts and tests; the UI polls snapshots)."""
        th = self._job_thread
        if th is not None:
            th.join(timeout)
        with self._lock:
            return self._job

    def _ct_failed_alarm(self) -> None:
        self._alarm_board.set("ct_failed", "the last CT could not be loaded (see the CT step)", float(self.clock()))

    def _set_job(self, progress: float, message: str, error: str | None = None, done: bool = False) -> None:
        with self._lock:
            name = self._job.name if self._job else "job"
            self._job = Job(name, progress, message, error, done)

    def _ct_job(self, path: str) -> None:
        try:
            from monotracker.ct import detect_fiducials, load_volume
        except ImportError as exc:
            self._set_job(1.0, "CT tools unavailable", f"CT tools are not installed: {exc}", True)
            self._ct_failed_alarm()
            self._bus.alert("alarm", "ct_failed", f"CT tools are not available: {exc}")
            return
        try:
            vol = load_volume(path)
            self._set_job(0.3, "detecting fiducials")
            det = detect_fiducials(vol)
            self._set_job(0.6, "extracting the head surface")
            try:
                from monotracker.ct import head_surface
            except ImportError:  # older ct package: no surface, the plan still works
                head_surface = None
            mesh = head_surface(vol) if head_surface is not None else None
        except MonoTrackerError as exc:
            self._set_job(1.0, "CT failed", str(exc), True)
            self._ct_failed_alarm()
            self._bus.alert("alarm", "ct_failed", f"CT could not be used: {exc}", {"path": path})
            return
        except Exception as exc:  # noqa: BLE001 - report, never kill the engine
            log.exception("CT job failed")
            self._set_job(1.0, "CT failed", f"internal error: {type(exc).__name__}: {exc}", True)
            self._ct_failed_alarm()
            self._bus.alert("alarm", "ct_failed", f"CT job failed: {type(exc).__name__}: {exc}", {"path": path})
            return
        with self._lock:
            self._volume = vol
            self._ct = CTSummary(path=path, shape=tuple(int(v) for v in vol.array.shape),
                                 spacing_mm=tuple(float(v) for v in vol.spacing_mm),
                                 notes=tuple(getattr(vol, "notes", ()) or ()))
            if mesh is not None:
                self._head_mesh = HeadMesh(frozen_array(np.asarray(mesh.vertices, float)),
                                           frozen_array(np.asarray(mesh.faces), np.int64))
                self._head_normals = np.asarray(mesh.vertex_normals, dtype=float)
            else:
                self._head_mesh = self._head_normals = None
            restored = self._plan.fiducials_locked and self._plan.ct_path == path
            if not restored:
                self._plan.ct_path = path
                self._plan.fiducials = [
                    PlanFiducial(i, np.asarray(f.centre_lps, float), float(f.radius_mm), float(f.score), "detected")
                    for i, f in enumerate(det.fiducials)
                ]
                self._plan.fiducials_locked = False
                self._plan.entry_lps_mm = None
                self._plan.target_lps_mm = None
                self._save_plan_locked("CT loaded")
        if not restored:
            self._loop.plan_changed("new CT loaded", restart_camera=False)
        self._set_job(1.0, "CT ready" if det.ok else f"CT ready; fiducials: {det.reason}", None, True)
        if restored:
            self._bus.event("ct_reloaded", f"CT reloaded for the saved plan: {path}", {"path": path})
        else:
            self._bus.event("fiducials_detected", f"{len(det.fiducials)} fiducials detected in the CT"
                            + ("" if det.ok else f" ({det.reason})"),
                            {"path": path, "ok": bool(det.ok), "reason": det.reason,
                             "centres_lps_mm": [np.asarray(f.centre_lps).tolist() for f in det.fiducials]})
            if not det.ok:
                self._bus.alert("warning", "fiducials_detection", f"fiducial detection: {det.reason}")

    # ================================================================== fiducials
    def set_fiducial_status(self, fid_id: int, status: str) -> CommandResult:
        """Operator decision on one fiducial: ``"confirmed" | "rejected" | "detected"`` (undo)."""
        if status not in ("confirmed", "rejected", "detected"):
            return _fail(f"status must be confirmed, rejected or detected, not {status!r}")
        with self._lock:
            if self._plan.fiducials_locked:
                return _fail("fiducials are locked; unlock them first")
            f = self._plan.fiducial(int(fid_id))
            if f is None:
                return _fail(f"no fiducial with id {fid_id}")
            if f.status == "added" and status == "detected":
                return _fail("an added fiducial can be confirmed or rejected, not set to detected")
            old, f.status = f.status, status
            self._save_plan_locked("fiducial status")
            centre = f.centre_lps_mm.tolist()
        self._bus.event(f"fiducial_{status}", f"fiducial {fid_id} {status} (was {old})",
                        {"id": int(fid_id), "centre_lps_mm": centre, "previous": old})
        return _ok(f"fiducial {fid_id} {status}")

    def add_fiducial(self, p_lps_mm, radius_mm: float | None = None) -> CommandResult:
        """Add an operator-picked fiducial centre (LPS mm); it counts as confirmed."""
        try:
            p = _point3(p_lps_mm)
        except InputError as exc:
            return _fail(str(exc))
        with self._lock:
            if self._plan.fiducials_locked:
                return _fail("fiducials are locked; unlock them first")
            radii = [f.radius_mm for f in self._plan.fiducials]
            r = float(radius_mm) if radius_mm is not None else (float(np.median(radii)) if radii else 4.0)
            if not (0 < r < 50):
                return _fail("fiducial radius must be between 0 and 50 mm")
            for f in self._plan.fiducials:
                if f.status != "rejected" and np.linalg.norm(f.centre_lps_mm - p) < 2 * r:
                    return _fail(f"too close to fiducial {f.id} ({np.linalg.norm(f.centre_lps_mm - p):.1f} mm)")
            fid = max((f.id for f in self._plan.fiducials), default=-1) + 1
            self._plan.fiducials.append(PlanFiducial(fid, p, r, 1.0, "added"))
            self._save_plan_locked("fiducial added")
        self._bus.event("fiducial_added", f"fiducial {fid} added by the operator", {"id": fid, "centre_lps_mm": p.tolist(),
                                                                                    "radius_mm": r})
        return _ok(f"fiducial {fid} added")

    def confirm_fiducials(self) -> CommandResult:
        """Lock the fiducial set (needs >= ``min_fiducials`` confirmed or added)."""
        with self._lock:
            if self._plan.fiducials_locked:
                return _ok("fiducials already locked")
            n = len(self._plan.usable_fiducials())
            need = self.config.min_fiducials
            if n < need:
                return _fail(f"{n} fiducials confirmed; at least {need} are needed")
            self._plan.fiducials_locked = True
            self._save_plan_locked("fiducials locked")
            ids = [f.id for f in self._plan.usable_fiducials()]
        self._bus.event("fiducials_locked", f"fiducial set locked ({n} fiducials: {ids})", {"ids": ids})
        return _ok(f"{n} fiducials locked")

    def unlock_fiducials(self) -> CommandResult:
        if self._loop.robot_state() not in ("disarmed", "estopped"):
            return _fail("disarm the robot before editing fiducials")
        with self._lock:
            if not self._plan.fiducials_locked:
                return _ok("fiducials not locked")
            self._plan.fiducials_locked = False
            self._save_plan_locked("fiducials unlocked")
        self._bus.event("fiducials_unlocked", "fiducial set unlocked for editing")
        self._loop.plan_changed("fiducials unlocked for editing", restart_camera=False)
        return _ok("fiducials unlocked")

    # ================================================================== path planning
    def set_entry(self, p_lps_mm) -> CommandResult:
        return self._set_path_point("entry", p_lps_mm)

    def set_target(self, p_lps_mm) -> CommandResult:
        return self._set_path_point("target", p_lps_mm)

    def use_sample_plan(self) -> CommandResult:
        """Entry/target of the phantom's sample plan (meant for the sample CT)."""
        from monotracker.sim.phantom import default_phantom

        ph = default_phantom()
        r = self.set_entry(ph.sample_entry_lps)
        return self.set_target(ph.sample_target_lps) if r.ok else r

    def _set_path_point(self, which: str, p_lps_mm) -> CommandResult:
        try:
            p = _point3(p_lps_mm)
        except InputError as exc:
            return _fail(str(exc))
        if self._loop.robot_state() == "tracking":
            return _fail("stop tracking before changing the path")
        with self._lock:
            if not self._plan.fiducials_locked:
                return _fail("confirm the fiducials before planning the path")
            other = self._plan.target_lps_mm if which == "entry" else self._plan.entry_lps_mm
            if other is not None and np.linalg.norm(other - p) < 1.0:
                return _fail("entry and target must be at least 1 mm apart")
            old = getattr(self._plan, f"{which}_lps_mm")
            setattr(self._plan, f"{which}_lps_mm", p)
            self._save_plan_locked(f"{which} set")
        self._bus.event(f"{which}_set", f"{which} set to ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm LPS",
                        {"lps_mm": p.tolist(), "previous": None if old is None else old.tolist()})
        if old is None or not np.array_equal(old, p):
            self._loop.plan_changed(f"{which} changed", restart_camera=True)
        return _ok(f"{which} set")

    # ================================================================== camera
    def set_camera(self, source: str, calibration_path: str | None = None) -> CommandResult:
        """Choose the frame source (and optional calibration file); applied by ``start_camera``."""
        return self._loop.set_camera(source, calibration_path)

    def start_camera(self) -> CommandResult:
        return self._loop.start_camera()

    def stop_camera(self) -> CommandResult:
        return self._loop.stop_camera()

    def latest_frame(self):
        """``(image BGR uint8, frame_index, PoseEstimate)`` of the newest processed frame, or None."""
        return self._loop.latest_frame()

    def volume(self):
        """The loaded CT :class:`~monotracker.ct.Volume` (LPS mm) for read-only display (slice
        views), or None while no CT is loaded. Never modify it: the engine owns it."""
        with self._lock:
            return self._volume

    def set_hand_eye(self, T_base_cam_mm) -> CommandResult:
        """Set the hand-eye transform (camera -> robot base, 4x4, mm) and save it in the plan."""
        T = np.asarray(T_base_cam_mm, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            return _fail("T_base_cam must be a finite 4x4 matrix")
        R = T[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or abs(np.linalg.det(R) - 1) > 1e-6:
            return _fail("T_base_cam is not a rigid transform")
        if self._loop.robot_state() == "tracking":
            return _fail("stop tracking before changing the hand-eye calibration")
        with self._lock:
            self._plan.T_base_cam = T.copy()
            self._save_plan_locked("hand-eye")
        self._bus.event("hand_eye_set", "hand-eye calibration T_base_cam set", {"T_base_cam_mm": T.tolist()})
        return _ok("hand-eye set")

    def _store_camera(self, source: str, calibration_path, K, dist, image_size) -> None:
        """Save the camera in use and its calibration in the plan (called by the loop)."""
        with self._lock:
            p = self._plan
            same = (p.camera_source == source and p.calibration_path == calibration_path and p.K is not None
                    and K is not None and np.array_equal(p.K, K))
            if same:
                return
            p.camera_source, p.calibration_path = source, calibration_path
            p.K = None if K is None else np.asarray(K, float).copy()
            p.dist = None if dist is None else np.asarray(dist, float).ravel().copy()
            p.image_size = None if image_size is None else tuple(int(v) for v in image_size)
            self._save_plan_locked("camera calibration")
        self._bus.event("camera_calibration", f"camera {source}: calibration stored in the plan",
                        {"source": source, "calibration_path": calibration_path,
                         "K": None if K is None else np.asarray(K).tolist(),
                         "dist": None if dist is None else np.asarray(dist).ravel().tolist(),
                         "image_size": None if image_size is None else list(image_size)})

    # ================================================================== robot
    def arm(self, pin) -> CommandResult:
        """Arm the robot; ``pin`` is the operator PIN (wrong tries count towards the lockout)."""
        r = self._check_pin(pin, "arm_refused", "arming")
        if not r.ok:
            return r
        return self._loop.arm()

    # ================================================================== control (browser clients)
    def _check_pin(self, pin, refused_code: str, what: str) -> CommandResult:
        """One PIN try through the shared :class:`PinGuard`: an audit row per wrong try (never the
        PIN), one ``pin_lockout`` alert when a lockout starts."""
        now = float(self.clock())
        was_locked = self._pin_guard.locked_for(now) > 0
        r = self._pin_guard.check("" if pin is None else str(pin), now)
        if r.ok:
            return r
        self._bus.event(refused_code, f"{what} refused: {r.message}", {"total_wrong": self._pin_guard.total_wrong},
                        level="warning")
        locked_s = self._pin_guard.locked_for(now)
        self._sync_pin_alarm(now)
        if locked_s > 0 and not was_locked:
            self._bus.alert("alarm", "pin_lockout", f"PIN locked for {locked_s:.0f} s after "
                            f"{self._pin_guard.max_tries} wrong tries", {"locked_s": locked_s})
        return r

    def _sync_pin_alarm(self, now: float) -> float:
        """``pin_lockout`` is active while the PIN is locked; returns the seconds left."""
        left = self._pin_guard.locked_for(now)
        if left > 0:
            self._alarm_board.set("pin_lockout", f"PIN locked for {left:.0f} s after {self._pin_guard.max_tries} "
                                  "wrong tries (arming and taking control)", now)
        else:
            self._alarm_board.clear("pin_lockout", now)
        return left

    def claim_control(self, client_id: str, pin, label: str = "") -> CommandResult:
        """Make browser client ``client_id`` the one in control (taking over from another client).

        ``pin``: the operator PIN (same guard and lockout as arming). ``label``: a display name for
        the other stations ("OR laptop", "nurse tablet"). Refused with one line on a wrong PIN or
        while locked. Already in control: ok without a PIN check."""
        client_id = str(client_id)
        if not client_id:
            return _fail("a client id is needed to take control")
        if self._control.is_controller(client_id):
            return _ok("already in control")
        r = self._check_pin(pin, "control_refused", "taking control")
        if not r.ok:
            return r
        prev, prev_label = self._control.claim(client_id, label, float(self.clock()))
        took = f" from {prev_label or prev}" if prev is not None else ""
        self._bus.event("control_taken", f"{label or client_id} took control{took}",
                        {"client": client_id, "label": label, "previous": prev, "previous_label": prev_label})
        return _ok("in control" + took)

    def release_control(self, client_id: str) -> CommandResult:
        """Client ``client_id`` gives up control (also when it disconnects); others stay unaffected."""
        if not self._control.release(str(client_id)):
            return _ok("not in control")
        self._bus.event("control_released", f"client {client_id} released control", {"client": str(client_id)})
        return _ok("control released")

    def is_in_control(self, client_id: str) -> bool:
        """True if browser client ``client_id`` is the one in control."""
        return self._control.is_controller(str(client_id))

    def control_summary(self):
        """:class:`~monotracker.engine.snapshot.ControlSummary` now (also in ``snap.control``)."""
        return self._control.summary(self._sync_pin_alarm(float(self.clock())))

    def for_client(self, client_id: str) -> ClientSession:
        """The session as browser client ``client_id`` may drive it (see ``engine/control.py``):
        reads as is, commands only while in control, ``estop()`` always."""
        return ClientSession(self, str(client_id))

    def disarm(self) -> CommandResult:
        return self._loop.disarm()

    def start_tracking(self) -> CommandResult:
        return self._loop.start_tracking()

    def stop_tracking(self) -> CommandResult:
        return self._loop.stop_tracking()

    def estop(self) -> CommandResult:
        return self._loop.estop()

    def reset_estop(self) -> CommandResult:
        return self._loop.reset_estop()

    def inject_fault(self, name: str) -> CommandResult:
        """Simulated sessions only: start a fault (see ``monotracker.sim.faults``)."""
        if name not in FAULTS:
            return _fail(f"unknown fault {name!r}; use one of {', '.join(FAULTS)}")
        return self._loop.inject_fault(name)

    # ================================================================== export
    def export_slicer_markups(self, folder) -> list[Path]:
        """Write fiducials and path as 3D Slicer markups (``.mrk.json``, LPS); returns the files."""
        from monotracker.engine.slicer import write_markups

        return write_markups(self.plan_copy(), Path(folder))

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
            fids = tuple(Fiducial(f.id, frozen_array(f.centre_lps_mm), f.radius_mm, f.score, f.status)
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
            alarms=self._alarm_board.active(float(self.clock())),
        )
