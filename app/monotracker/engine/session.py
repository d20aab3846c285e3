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
    s.set_ball_finish("matte" | "glossy" | "read" | None)   # the kit's balls' finish, kept in the plan
                                        #   (None: the launch setting); trust rules, so refused while armed;
                                        #   a running camera restarts with it
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
    s.plan_not_ready() -> str | None    # why arming/tracking is refused (plan checks, CT loaded, re-confirmation)
    s.reconfirm_plan()                  # the operator re-confirms after an integrity alarm (edited outside, CT/calibration changed)
    s.integrity_alarms() -> [(code, line)]   # integrity conditions that stand until they clear (for snap.alarms)
    s.arm(pin); s.disarm()               # arm needs a fresh trusted pose for this plan; wrong PINs: 5 tries, then a 30 s lockout (doubling), see engine/access.py
    s.claim_control(client_id, pin, label=""); s.release_control(client_id)   # one browser client in control
    s.for_client(client_id) -> ClientSession    # reads as is; commands only while in control; estop() always
    s.start_tracking(); s.stop_tracking()   # needs armed + plan + trusted fresh pose + hand-eye
    s.estop(); s.reset_estop()          # e-stop is latched; reset leaves the arm disarmed; estop() waits
                                        #   (~1 s at most) for the robot controller's acknowledgement
    s.request_estop()                   # the stop channel alone: never blocks (a web server's event loop)
    s.inject_fault(name)                # sim only: "camera-freeze"|"occlude-all"|"robot-disconnect"|"bad-pose"|"camera-bump"|"camera-sag"|"none"
    s.export_slicer_markups(folder) -> list[Path]   # .mrk.json, LPS
    s.plan_layout(n_balls=9, quick=False, noise_px=None)   # async job: where the balls and the camera go
                                        #   for a small error at the target (monotracker.planning); progress and
                                        #   result in snap.layout; refused while armed/tracking/holding
    s.cancel_layout()                   # stop it; the previous layout stays
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
    snap.layout           # None or LayoutSummary(job, balls_lps_mm, T_ct_cam, suggestion, current, balls_needed,
                          #   candidates_lps_mm, error_map_mm, stale, ...): the last planned layout
    snap.alerts           # recent alerts (Event: t, t_session, kind, level "info"|"warning"|"alarm", code, message, data)
    s.volume()            # the loaded CT Volume (LPS mm) for read-only display, or None
    s.latest_frame()      # (image BGR uint8, frame_index, estimate) for the overlay, or None; estimate is
                          #   vision's PoseEstimate (image_points_px per fiducial, status, residuals) for
                          #   "sim" and real cameras, the engine's PoseSample for "sim-points"
    s.subscribe(callback) # callback(Event) on every alert/event (engine thread); returns unsubscribe()
    s.audit_entries(limit=None) -> list[AuditEntry]

One session per folder: the session locks its ``home`` (``engine/session_lock.py``); a second
session on it raises :class:`~monotracker.engine.session_lock.SessionFolderBusy` naming the holder.

Seams for programs beside the UI (recording, OpenIGTLink, the demo, benchmarks), instead of the
engine's parts (every listener runs on the engine thread: keep it short; one that raises is
logged and never disturbs the loop)::

    s.add_pose_listener(fn) -> remove()   # fn(sample: PoseSample, trusted: bool, now_s) per estimate handled
    s.add_tick_listener(fn) -> remove()   # fn(t_s) after every control tick (clock="sim")
    s.latest_pose() -> PoseRecord | None  # newest estimate and its verdict (sample, trusted, code, reason)
    s.robot_status() -> RobotStatus | None   # the arm now (state, q rad, T_base_tip mm, speed): None before it connects
    s.needle_target() -> (T_base_target 4x4 mm | None, capture stamp s | None)   # last handed to the tracker
    s.recent_alerts(n=50) -> list[Event]  # newest last
    s.latencies_s() -> tuple[float, ...]  # capture -> command latency of each command, s
    s.truth_T_base_ct(t) -> 4x4 mm | None # the simulator's true head pose in the robot base (None: real camera)

Alert codes the UI can rely on, with their levels: the module docstring of ``engine/alarms.py``
(every code that can be an active condition has a row in its catalogue). Camera sources: the
table of source kinds, ``engine/rigs/sources.py``.

Composition: ``Session`` inherits nothing. It builds its parts and hands each its collaborators:
the event bus and audit log (``events.py``, ``audit.py``), the alarms (``alarms.py``), the plan
store and editor (``plan/``), the CT job (``ct_job.py``), who may drive it (``access.py``), the
tracking loop (``loop/``, with its rigs from ``rigs/``), the recording (``recording.py``) and the
layout job (``layout_job.py``); the
methods below are one-line delegations to them (``docs/engine.md`` draws the layout).

Threading: every public method may be called from any thread (viser callbacks). State lives
behind one re-entrant lock; methods hold it only for bookkeeping and for the plan's atomic save
(a few ms: a command saves the new plan first and swaps it in only once it is on disk, so the file
and the in-memory plan never disagree), never across CT loading, registration or robot motion.
The audit log is written by its own thread from a bounded queue: no command waits on it.
Snapshots are copies with read-only arrays.

Validation: one check per kind of plan state (``engine/plan/checks.py``), used by the commands,
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

from monotracker.engine.access import Access, ClientSession
from monotracker.engine.alarms import Alarms, level_of
from monotracker.engine.audit import AuditEntry, AuditLog
from monotracker.engine.config import SessionConfig
from monotracker.engine.ct_job import CTJob
from monotracker.engine.events import Event, EventBus
from monotracker.engine.layout_job import LayoutJob
from monotracker.engine.loop import SimClock, TrackingLoop
from monotracker.engine.loop.core import PoseRecord
from monotracker.engine.plan import Plan, angle_to_skin_normal_deg, distance_segment_to_points_mm, path_length_mm
from monotracker.engine.plan.editor import PlanEditor
from monotracker.engine.plan.store import PlanStore, home_write_problem, prepare_home
from monotracker.engine.recording import Recording
from monotracker.engine.rigs.base import RobotStatus
from monotracker.engine.session_lock import SessionFolderLock
from monotracker.engine.snapshot import CommandResult, Fiducial, Job, PlanSummary, Snapshot, frozen_array
from monotracker.errors import MonoTrackerError

log = logging.getLogger(__name__)

PLAN_FILE = "plan.json"
AUDIT_FILE = "audit.sqlite"

__all__ = ["AUDIT_FILE", "PLAN_FILE", "Session", "SimClock"]


class Session:
    """One surgical session (see the module docstring for the whole API)."""

    def __init__(self, config: SessionConfig | None = None, *, camera_factory=None, robot_factory=None):
        """``camera_factory(source, calibration_path, plan, cfg, session) -> CameraRig`` and
        ``robot_factory(cfg, session) -> RobotRig`` replace the default vision/robot wiring
        (``monotracker.engine.rigs.factory``), e.g. for tests on doubles."""
        from monotracker.paths import data_dir

        self.camera_factory = camera_factory
        self.robot_factory = robot_factory
        self.config = config or SessionConfig()
        self.config.validate()
        self.home = Path(self.config.home) if self.config.home is not None else data_dir()
        prepare_home(self.home)
        # one session per folder: a second one is refused naming the holder (engine/session_lock.py)
        self._folder_lock = SessionFolderLock(self.home).acquire()
        self.session_id = uuid.uuid4().hex[:12]
        self.clock = SimClock() if self.config.clock == "sim" else time.monotonic
        self._lock = threading.RLock()  # the state lock: plan, CT, job (held for bookkeeping only)
        self._started = False
        self._closed = False
        # ---- the parts, each given its collaborators
        self._audit = AuditLog(self.home / AUDIT_FILE, self.session_id,
                               on_problem=lambda level, code, msg, data: self._bus.alert(level, code, msg, data))
        self._bus = EventBus(sink=self._audit.record_event, clock=self.clock, alert_level=level_of)
        self._alarms = Alarms(self._bus, self.clock)
        self._store = PlanStore(self.home / PLAN_FILE, self.home, self._bus, audit=self._audit)
        self._plan = PlanEditor(self._store, lock=self._lock, events=self._bus, alarms=self._alarms.board,
                                clock=self.clock, config=self.config, ct=lambda: self._ct.loaded,
                                robot_state=lambda: self._loop.robot.state(),
                                plan_changed=lambda why, restart: self._loop.camera.plan_changed(why, restart),
                                forget_ct=lambda: self._ct.forget(), audit=self._audit,
                                disarm_for_revision=lambda why: self._loop.robot.disarm_for_revision(why))
        self._ct = CTJob(lock=self._lock, editor=self._plan, events=self._bus, alarms=self._alarms.board,
                         clock=self.clock, config=self.config,
                         plan_changed=lambda why, restart: self._loop.camera.plan_changed(why, restart))
        self._access = Access(self.config.arm_pin, events=self._bus, alarms=self._alarms.board, clock=self.clock,
                              session=self)
        unwritable = home_write_problem(self.home)
        if unwritable:
            self._store.home_unwritable = unwritable
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
        self._plan.restore()
        ct_path = self._store.plan.ct_path
        if ct_path and not Path(ct_path).exists():
            self._bus.alert("alarm", "plan_ct_missing", f"the plan's CT {ct_path} is missing; the plan cannot be "
                            "checked or armed until it is back (or start a new plan)", {"path": ct_path})
        self._loop = TrackingLoop(config=self.config, clock=self.clock, events=self._bus, alarms=self._alarms,
                                  plan=self._plan, access=self._access, session=self)
        self._recording = Recording(self, self._loop, self._lock)
        self._layout = LayoutJob(lock=self._lock, editor=self._plan, ct=lambda: self._ct.loaded,
                                 ct_job=lambda: self._ct.job, robot_state=lambda: self._loop.robot.state(),
                                 camera_rig=lambda: self._loop.camera.rig, config=self.config, events=self._bus)
        self._bus.event("session_started", f"session {self.session_id} started, disarmed",
                        {"home": str(self.home), "camera": self.config.camera, "robot": self.config.robot,
                         "clock": self.config.clock, "plan_revision": self._store.plan.revision})
        self._note_folder_lock()

    # ================================================================== lifecycle
    def start(self) -> CommandResult:
        """Start the engine threads (event dispatcher; camera/control threads when running)."""
        with self._lock:
            if self._closed:
                return CommandResult.refused("session is shut down")
            if self._started:
                return CommandResult.done("already started")
            self._started = True
        self._bus.start()
        self._loop.start_threads()
        # After a restart the plan is back but the CT volume and surface are not: reload them in
        # the background for the views (the saved fiducials are kept, see load_ct).
        with self._lock:
            ct_path = self._store.plan.ct_path if self._ct.loaded is None else None
        if ct_path and Path(ct_path).exists():
            self.load_ct(ct_path)
        return CommandResult.done("started")

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

    # ================================================================== events and alarms
    def subscribe(self, callback) -> "callable":
        """``callback(event)`` for every later event/alert; returns the unsubscribe function."""
        return self._bus.subscribe(callback)

    def alert(self, level: str, code: str, message: str, data: dict | None = None) -> Event | None:
        """Raise an alert (to subscribers and the audit log); used by the engine's parts and rigs.
        See :meth:`monotracker.engine.alarms.Alarms.alert` (a catalogued code carries its row's level)."""
        return self._alarms.alert(level, code, message, data)

    def clear_condition(self, code: str) -> None:
        """A camera setup condition (``camera_setup`` rows of ``alarms.CATALOGUE``) raised with
        :meth:`alert` no longer holds (thread-safe)."""
        self._alarms.clear(code)

    def record(self, code: str, message: str, data: dict | None = None, level: str = "info") -> Event:
        """Record a decision/state change (to subscribers and the audit log)."""
        return self._bus.event(code, message, data, level)

    def audit_entries(self, limit: int | None = None, code: str | None = None) -> list[AuditEntry]:
        """Rows of the audit log (all sessions in this home), oldest first. Waits (at most 5 s)
        for the rows still queued; rows delayed to a spill file appear once copied back in."""
        return self._audit.entries(code=code, limit=limit)

    def recent_alerts(self, n: int = 50) -> list[Event]:
        """The newest ``n`` alerts (``Event``), newest last."""
        return self._bus.recent("alert")[-int(n):] if n > 0 else []

    def integrity_alarms(self) -> list[tuple[str, str]]:
        """Integrity conditions that stand until they clear, as ``(code, one line)``, most serious
        first: the session folder is unwritable, the plan needs re-confirmation, the plan's CT is
        missing, the audit log no longer matches its anchor, audit rows were lost or are delayed,
        this machine's integrity key is unavailable. For the active-alarm list (``snap.alarms``);
        each was also raised once as an alert when it began."""
        out = self._plan.integrity_alarms()
        audit = self._audit
        if audit.tampered:
            out.append(("audit_tampered", f"audit log {audit.path.name}: {audit.tampered}"))
        if audit.lost:
            out.append(("audit_lost", f"{audit.lost} audit rows were lost"))
        elif audit.open_error or getattr(audit, "_trouble", False):
            out.append(("audit_delayed", f"audit rows are delayed to {audit.spill_path} ({audit.delayed} so far)"))
        key = audit.key
        if key is not None and key.problem:
            out.append(("integrity_key_unavailable", f"{key.problem}: changes outside the app are seen through "
                        "the audit chain only"))
        return out

    # ================================================================== seams for programs beside the UI
    def add_pose_listener(self, fn) -> "callable":
        """``fn(sample, trusted, now)`` after every estimate the engine handles (``PoseSample``,
        its verdict, session s); on the engine thread: keep it short. Returns the remover."""
        return self._loop.add_pose_hook(fn)

    def add_tick_listener(self, fn) -> "callable":
        """``fn(t)`` after every control tick of a clock="sim" session (session s). Returns the remover."""
        return self._loop.add_tick_hook(fn)

    def latest_pose(self) -> PoseRecord | None:
        """The newest estimate the engine handled and its trust verdict, or None."""
        return self._loop.latest

    def robot_status(self) -> RobotStatus | None:
        """The arm now (``RobotStatus``: state, q rad, T_base_tip mm, speed mm/s), or None while no
        robot is connected."""
        rob = self._loop.robot.rig
        return None if rob is None else rob.status()

    def needle_target(self) -> tuple:
        """``(T_base_target 4x4 mm or None, its capture stamp s or None)``: the needle target last
        handed to the tracker."""
        return self._loop.target()

    def latencies_s(self) -> tuple[float, ...]:
        """Capture -> command latency of every control command so far (s, oldest first, at most 5000)."""
        return tuple(self._loop.latencies_s)

    def truth_T_base_ct(self, t: float):
        """The simulator's true head (CT) pose in the robot base at session time ``t`` (4x4 mm), or
        None for a real camera or no camera."""
        rig = self._loop.camera.rig
        return None if rig is None else rig.truth_T_base_ct(t)

    # ================================================================== plan
    @property
    def plan_path(self) -> Path:
        """Where the plan is saved: ``plan.json`` in the session's ``home``."""
        return self._store.path

    def plan_copy(self) -> Plan:
        """A deep copy of the current plan."""
        return self._plan.copy()

    def new_plan(self) -> CommandResult:
        """Forget CT, fiducials, path (calibrations are kept). Refused while armed."""
        return self._plan.new_plan()

    def set_fiducial_status(self, fid_id: int, status: str) -> CommandResult:
        """See :meth:`PlanEditor.set_fiducial_status <monotracker.engine.plan.editor.PlanEditor.set_fiducial_status>`."""
        return self._plan.set_fiducial_status(fid_id, status)

    def add_fiducial(self, p_lps_mm, radius_mm: float | None = None, manual: bool = False) -> CommandResult:
        """See :meth:`PlanEditor.add_fiducial <monotracker.engine.plan.editor.PlanEditor.add_fiducial>` (LPS mm)."""
        return self._plan.add_fiducial(p_lps_mm, radius_mm, manual)

    def confirm_fiducials(self) -> CommandResult:
        """Lock the fiducial set (needs >= ``config.min_fiducials`` confirmed or added)."""
        return self._plan.confirm_fiducials()

    def set_fiducial_role(self, fid_id: int, role: str) -> CommandResult:
        """``"registration"`` or ``"validation"`` (kept out of the fit, verifies it)."""
        return self._plan.set_fiducial_role(fid_id, role)

    def unlock_fiducials(self) -> CommandResult:
        """Back to editing the fiducials (refused while armed or tracking)."""
        return self._plan.unlock_fiducials()

    def set_ball_finish(self, finish: str | None) -> CommandResult:
        """The kit's balls' finish for this patient, kept in the plan ("matte", "glossy", "read"
        or None: the launch setting); a running camera is restarted with it (see
        ``PlanEditor.set_ball_finish``)."""
        rig = self._loop.camera.rig
        running = rig is not None and rig.running
        r = self._plan.set_ball_finish(finish)
        if r.ok and running:
            return CommandResult.done(f"{r.message}; the camera restarted with it")
        return r

    def set_entry(self, p_lps_mm) -> CommandResult:
        """The needle's entry point, (3,) CT LPS mm (see ``PlanEditor.set_entry``)."""
        return self._plan.set_entry(p_lps_mm)

    def set_target(self, p_lps_mm) -> CommandResult:
        """The target point, (3,) CT LPS mm (see ``PlanEditor.set_target``)."""
        return self._plan.set_target(p_lps_mm)

    def use_sample_plan(self) -> CommandResult:
        """Entry/target of the phantom's sample plan (meant for the sample CT)."""
        return self._plan.use_sample_plan()

    def set_hand_eye(self, T_base_cam_mm) -> CommandResult:
        """``T_base_cam`` (4x4, camera -> robot base, mm), saved in the plan."""
        return self._plan.set_hand_eye(T_base_cam_mm)

    def plan_not_ready(self) -> str | None:
        """Why arming/tracking is refused (one line), or None."""
        return self._plan.plan_not_ready()

    def reconfirm_plan(self) -> CommandResult:
        """The operator re-confirms the plan after an integrity alarm."""
        return self._plan.reconfirm_plan()

    def export_slicer_markups(self, folder) -> list[Path]:
        """Write fiducials and path as 3D Slicer markups (``.mrk.json``, LPS); returns the files."""
        from monotracker.engine.plan.slicer import write_markups

        return write_markups(self.plan_copy(), Path(folder))

    # ================================================================== CT
    def load_ct(self, path, series: str | None = None) -> CommandResult:
        """Start the CT job (load, detect fiducials, head surface); see ``CTJob.load_ct``."""
        return self._ct.load_ct(path, series)

    def load_sample_ct(self) -> CommandResult:
        """:meth:`load_ct` on the bundled phantom CT."""
        return self._ct.load_sample_ct()

    def set_fiducial_kit(self, radius_mm, density_hu=None) -> CommandResult:
        """The fiducial kit (ball radius mm, density HU or None), kept in the plan; with a CT the
        fiducials are detected again (see ``CTJob.set_fiducial_kit``)."""
        return self._ct.set_fiducial_kit(radius_mm, density_hu)

    def cancel_ct_job(self) -> CommandResult:
        """Stop the CT job; the previous CT and plan stay."""
        return self._ct.cancel_ct_job()

    def wait_for_job(self, timeout: float | None = None) -> Job | None:
        """Block until the current job ends (s; None = no limit); the last :class:`Job` or None."""
        return self._ct.wait_for_job(timeout)

    # ================================================================== layout (issue 31)
    def plan_layout(self, n_balls: int = 9, quick: bool = False, noise_px: float | None = None) -> CommandResult:
        """Plan where ``n_balls`` fiducial balls and the camera go for a small error at the
        target, on a job thread (progress and result in ``snap.layout``); see ``LayoutJob.start``
        for the refusals (robot armed/tracking/holding, no CT or target, busy)."""
        return self._layout.start(n_balls, quick, noise_px)

    def cancel_layout(self) -> CommandResult:
        """Stop the layout job; the previous layout (if any) stays."""
        return self._layout.cancel()

    def wait_for_layout(self, timeout: float | None = None) -> Job | None:
        """Block until the layout job ends (s; None = no limit); its last :class:`Job` or None."""
        return self._layout.wait(timeout)

    def volume(self):
        """The loaded CT :class:`~monotracker.ct.Volume` (LPS mm) for read-only display (slice
        views), or None while no CT is loaded. Never modify it: the engine owns it."""
        with self._lock:
            loaded = self._ct.loaded
            return None if loaded is None else loaded.volume

    # ================================================================== who may drive it
    def claim_control(self, client_id: str, pin, label: str = "") -> CommandResult:
        """Make browser client ``client_id`` the one in control (operator PIN)."""
        return self._access.claim_control(client_id, pin, label)

    def release_control(self, client_id: str) -> CommandResult:
        """Client ``client_id`` gives up control."""
        return self._access.release_control(client_id)

    def is_in_control(self, client_id: str) -> bool:
        """True if browser client ``client_id`` is the one in control."""
        return self._access.is_in_control(client_id)

    def control_summary(self):
        """:class:`~monotracker.engine.snapshot.ControlSummary` now (also in ``snap.control``)."""
        return self._access.control_summary()

    def for_client(self, client_id: str) -> ClientSession:
        """The session as browser client ``client_id`` may drive it (``engine/access.py``)."""
        return self._access.for_client(client_id)

    def report_login_lockout(self, locked_s: float, message: str = "") -> None:
        """The page login is locked for ``locked_s`` s (0: no longer locked)."""
        self._access.report_login_lockout(locked_s, message)

    # ================================================================== camera
    def set_camera(self, source: str, calibration_path: str | None = None) -> CommandResult:
        """Choose the frame source (``engine/rigs/sources.py``) and calibration; see ``CameraControl.set_camera``."""
        return self._loop.camera.set_camera(source, calibration_path)

    def start_camera(self) -> CommandResult:
        """Start the pose stream (poses in ``snap.pose``); see ``CameraControl.start_camera``."""
        return self._loop.camera.start_camera()

    def stop_camera(self) -> CommandResult:
        """Stop the pose stream; the pose is cleared and a tracking arm holds. Never refused."""
        return self._loop.camera.stop_camera()

    def latest_frame(self):
        """``(image BGR uint8, frame_index, estimate)`` of the newest processed frame, or None."""
        return self._loop.camera.latest_frame()

    def learn_ball_colour(self, x_px: float, y_px: float, *, frame=None, frame_index: int | None = None) -> CommandResult:
        """Learn the balls' colour from a click (px) on a ball; see ``CameraControl.learn_ball_colour``."""
        return self._loop.camera.learn_ball_colour(x_px, y_px, frame=frame, frame_index=frame_index)

    def inject_fault(self, name: str) -> CommandResult:
        """Simulated sessions only: start a fault (``config.FAULTS``; "none" clears)."""
        return self._loop.camera.inject_fault(name)

    # ================================================================== robot
    def arm(self, pin) -> CommandResult:
        """Arm the robot with the operator ``pin``; see ``RobotControl.arm`` for the refusals."""
        return self._loop.robot.arm(pin)

    def disarm(self) -> CommandResult:
        """Disarm from armed, tracking or holding. Refused while the e-stop is latched."""
        return self._loop.robot.disarm()

    def start_tracking(self) -> CommandResult:
        """The arm follows the planned path as the head moves; see ``RobotControl.start_tracking``."""
        return self._loop.robot.start_tracking()

    def stop_tracking(self) -> CommandResult:
        """The arm stops following and holds, still armed."""
        return self._loop.robot.stop_tracking()

    def estop(self) -> CommandResult:
        """Emergency stop: the arm stops at once and the stop is latched (``alarm`` ``estop``)
        until :meth:`reset_estop`. Never refused, also without a robot. The stop goes first,
        straight to the robot's controller (:meth:`request_estop`); the call then waits (about a
        second at most) for the controller's acknowledgement: ``ok`` when it confirmed the stop,
        else ``ok=False`` with the ``estop_unconfirmed`` alarm (use the robot's own e-stop)."""
        return self._loop.robot.estop()

    def request_estop(self) -> None:
        """The stop channel alone: latch the e-stop in the robot's controller and return at once,
        without a lock the engine or vision may hold, without waiting for the acknowledgement or
        writing the audit (:meth:`estop` does both). For a web server's event loop, so a STOP is
        never queued behind other work (``engine/pipeline_priority.py``). Never raises."""
        self._loop.robot.signal_estop()

    def reset_estop(self) -> CommandResult:
        """Release a latched e-stop; the arm is left disarmed."""
        return self._loop.robot.reset_estop()

    def connect_robot(self) -> CommandResult:
        """Connect the arm without arming it (e.g. for hand-eye poses); it stays DISARMED."""
        return self._loop.robot.connect()

    # ================================================================== recording
    def start_recording(self, folder) -> CommandResult:
        """Record every estimated frame and what the engine made of it into ``folder`` (an empty or
        new folder; layout in ``docs/interop.md``) until :meth:`stop_recording` or shutdown."""
        return self._recording.start(folder)

    def stop_recording(self) -> CommandResult:
        """Close the recording (manifest marked complete). Idempotent."""
        return self._recording.stop()

    # ================================================================== snapshot
    def _plan_summary(self, plan: Plan, loaded) -> PlanSummary:
        e, t = plan.entry_lps_mm, plan.target_lps_mm
        if e is None or t is None:
            return PlanSummary(frozen_array(e), frozen_array(t), None, None, None, False)
        ang = None
        if loaded is not None and loaded.head_mesh is not None and loaded.head_normals is not None:
            ang = angle_to_skin_normal_deg(e, t, loaded.head_mesh.vertices, loaded.head_normals)
        return PlanSummary(frozen_array(e), frozen_array(t), path_length_mm(e, t), ang,
                           distance_segment_to_points_mm(e, t, plan.fiducial_centres()), True)

    def snapshot(self) -> Snapshot:
        """An immutable, consistent copy of the session state (thread-safe, cheap)."""
        with self._lock:
            plan = self._store.plan
            loaded = self._ct.loaded
            fids = tuple(Fiducial(f.id, frozen_array(f.centre_lps_mm), f.radius_mm, f.score, f.status, f.role)
                         for f in plan.fiducials)
            plan_summary = self._plan_summary(plan, loaded)
            job, locked = self._ct.job, plan.fiducials_locked
            layout = self._layout.summary()
            ct, mesh = (None, None) if loaded is None else (loaded.summary, loaded.head_mesh)
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
            alerts=tuple(self.recent_alerts(50)), plan_path=str(self._store.path),
            audit_path=str(self._audit.path), control=self.control_summary(),
            alarms=self._alarms.active(dict(self.integrity_alarms())),
            recording=self._recording.summary(), layout=layout, plan_ct_path=plan.ct_path,
            ball_finish=plan.ball_finish, ball_finish_default=str(self.config.ball_finish),
        )
