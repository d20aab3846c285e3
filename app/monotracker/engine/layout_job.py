"""The session's layout job: plan where the fiducial balls and the camera go (issue 31), off the
UI threads, with progress and cancel; the result in ``snap.layout``.

:class:`LayoutJob` is a part of the :class:`~monotracker.engine.session.Session`. It reads the
loaded CT's head surface, the plan's target (and entry) and registration fiducials, the camera
model the session would register with and the session's trust rules (``frame_rules``), builds a
:class:`~monotracker.planning.PlanningProblem` with the planner's room defaults
(:func:`~monotracker.planning.build_problem`) and runs :func:`~monotracker.planning.plan_layout`
on its own thread. It changes nothing in the plan: the suggestion is advice, shown at the Plan
step, and the Register step compares the live camera with the planned placement
(:func:`placement_offset`).

Refused while the robot is armed, tracking or holding (planning takes seconds of CPU the pose
stream needs), and arming while it runs stops it at its next step. Cancel: :meth:`LayoutJob.cancel`
(the progress callback raises; the previous result stays). A failure is one line in
``snap.layout.job.error``, never a traceback. Units: LPS mm, px; ``T_ct_cam`` camera -> CT.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from monotracker.engine.ct_job import JobCancelled, JobToken
from monotracker.engine.snapshot import (
    CommandResult,
    Job,
    LayoutError,
    LayoutExpectation,
    LayoutSummary,
    frozen_array,
)

log = logging.getLogger(__name__)

#: robot states in which no layout is planned (and which stop a running one)
BUSY_ROBOT_STATES = ("armed", "tracking", "holding")
#: camera directions tried by a quick plan (the CLI's --quick) and by a full one
QUICK_DIRECTIONS, FULL_DIRECTIONS = 8, 24
#: the longest a plan may run (s, wall clock) before it is stopped with a one-line reason; a full
#: plan takes ~40 s on a quiet 2-core machine, so this is several times that: a plan still running
#: then is starved of CPU or stuck, and the operator is told so instead of watching a bar that never ends
TIME_LIMIT_S = 300.0


def placement_offset(T_ct_cam_planned, T_cam_ct_now) -> tuple[float, float]:
    """How far the live camera is from the planned placement: ``(mm, deg)``, the distance
    between the two camera centres (CT mm) and the angle between their viewing axes (deg).

    Args:
        T_ct_cam_planned: 4x4, the planned camera -> CT (mm).
        T_cam_ct_now: 4x4, the live pose CT -> camera (mm), as ``snap.pose.T_cam_ct``.
    """
    P = np.asarray(T_ct_cam_planned, float)
    N = np.asarray(T_cam_ct_now, float)
    R, t = N[:3, :3], N[:3, 3]
    eye_now = -R.T @ t  # the live camera's centre in the CT
    look_now = R.T @ np.array([0.0, 0.0, 1.0])
    d = float(np.linalg.norm(eye_now - P[:3, 3]))
    c = float(np.clip(look_now @ P[:3, 2], -1.0, 1.0))
    return d, float(np.degrees(np.arccos(c)))


def planning_camera(plan, rig):
    """The camera model a layout is planned with (a :class:`~monotracker.vision.camera_model.CameraModel`):
    the plan's calibration, else the camera rig's (``rig`` may be None), else the simulated
    camera's (``default_camera``); an unusable calibration is skipped."""
    from monotracker.errors import MonoTrackerError
    from monotracker.vision.camera_model import CameraModel, default_camera

    for K, dist, size in ((plan.K, plan.dist, plan.image_size),
                          (None, None, None) if rig is None else (rig.K, rig.dist, rig.image_size)):
        if K is not None and size is not None:
            try:
                return CameraModel(np.asarray(K, float), np.zeros(5) if dist is None else np.asarray(dist, float),
                                   tuple(int(v) for v in size))
            except MonoTrackerError:
                continue
    return default_camera()


def _error(e) -> LayoutError | None:
    if e is None:
        return None
    return LayoutError(int(e.n_balls), float(e.mean_mm), float(e.p95_mm), float(e.rms_mm), float(e.trusted))


def expectation(pred) -> LayoutExpectation | None:
    """A :class:`~monotracker.planning.Prediction` as the snapshot's :class:`LayoutExpectation`."""
    if pred is None:
        return None
    lo = pred.with_losses
    return LayoutExpectation(int(len(pred.centres)), int(pred.visibility.count), _error(pred.all_seen),
                             _error(pred.worst_hidden), None if pred.worst_ball is None else int(pred.worst_ball),
                             pred.reason or pred.margin_reason,
                             None if lo is None else float(lo.found_probability),
                             None if lo is None else float(lo.trusted), None if lo is None else float(lo.pose),
                             None if lo is None or lo.found_short is None else float(lo.found_short),
                             0 if lo is None else int(lo.short_of_skin))


class LayoutJob:
    """The layout job (see the module docstring). Collaborators: the state ``lock``, the plan
    ``editor`` (read only), ``ct()`` the loaded CT (:class:`~monotracker.engine.ct_job.LoadedCT`
    or None), ``ct_job()`` the CT job's :class:`Job` or None, ``robot_state()``, ``camera_rig()``
    the running camera rig or None (:func:`planning_camera`), the session ``config``
    (``frame_rules()``) and the event bus."""

    def __init__(self, *, lock, editor, ct, ct_job, robot_state, camera_rig, config, events,
                 time_limit_s: float = TIME_LIMIT_S, clock=time.monotonic):
        self._lock = lock
        self.time_limit_s = float(time_limit_s)  # s, see TIME_LIMIT_S
        self._clock = clock  # s, monotonic
        self._editor = editor
        self._ct = ct
        self._ct_job = ct_job
        self._robot_state = robot_state
        self._camera_rig = camera_rig
        self.config = config
        self._bus = events
        self._job: Job | None = None
        self._token: JobToken | None = None
        self._thread: threading.Thread | None = None
        self._result: LayoutSummary | None = None  # the last finished plan (its job field unused)
        self._basis = None  # what the last finished plan was made for (stale when it differs)

    # ------------------------------------------------------------------ commands
    def start(self, n_balls: int = 9, quick: bool = False, noise_px: float | None = None) -> CommandResult:
        """Plan ``n_balls`` balls (4-16) and the camera for the current plan's target; ``quick``:
        8 camera directions and no refinement (seconds instead of tens of seconds); ``noise_px``
        the image noise of the ball centres (px; None: the planner's 0.2). Progress in
        ``snap.layout.job``; :meth:`wait` waits for it.

        Refuses (ok=False, one line): the robot is armed/tracking/holding; a layout or CT job
        is running; no CT or no head surface; no target; a bad count or noise."""
        from monotracker.planning import DEFAULT_NOISE_PX
        from monotracker.planning.planner import MAX_BALLS

        cfg = self.config.frame_rules()
        try:
            n = int(n_balls)
            if n != n_balls:
                raise ValueError
        except (TypeError, ValueError):
            return CommandResult.refused(f"ball count must be a whole number, got {n_balls!r}")
        if not cfg.min_fiducials <= n <= MAX_BALLS:
            return CommandResult.refused(f"ball count must be {cfg.min_fiducials}-{MAX_BALLS}, got {n}")
        noise = DEFAULT_NOISE_PX if noise_px is None else noise_px
        try:
            noise = float(noise)
        except (TypeError, ValueError):
            return CommandResult.refused(f"image noise must be a number of px, got {noise_px!r}")
        if not (np.isfinite(noise) and 0.005 <= noise <= 5.0):
            return CommandResult.refused(f"image noise {noise_px} px is implausible (0.005-5 px)")
        state = self._robot_state()
        if state in BUSY_ROBOT_STATES:
            return CommandResult.refused(f"the robot is {state}: disarm it before planning the layout "
                                         "(planning takes the CPU the pose stream needs)")
        with self._lock:
            if self._job is not None and not self._job.done:
                return CommandResult.refused("busy: the layout is still being planned (cancel it first)")
            ct_job = self._ct_job()
            if ct_job is not None and not ct_job.done:
                return CommandResult.refused(f"busy: {ct_job.name} is still running")
            loaded = self._ct()
            if loaded is None:
                return CommandResult.refused("load a CT first: the layout is planned on its head surface")
            if loaded.head_mesh is None:
                return CommandResult.refused("the CT has no head surface to put balls on")
            plan = self._editor.plan
            if plan.target_lps_mm is None:
                return CommandResult.refused("set the target first: the layout is planned for the error there")
            fids = plan.registration_fiducials()
            basis = self._basis_of(plan, loaded)
            kit = plan.fiducial_kit
            radius = (float(kit.radius_mm) if kit is not None else
                      float(np.median([f.radius_mm for f in fids])) if fids else 4.0)
            args = dict(head_mesh=loaded.head_mesh, target=np.array(plan.target_lps_mm, float),
                        entry=None if plan.entry_lps_mm is None else np.array(plan.entry_lps_mm, float),
                        existing=np.array([f.centre_lps_mm for f in fids], float).reshape(-1, 3),
                        existing_ids=tuple(int(f.id) for f in fids), radius_mm=radius,
                        camera=planning_camera(plan, self._camera_rig()),
                        noise_px=noise, n_balls=n, quick=bool(quick),
                        rules=self.config.frame_rules(plan.ball_finish))   # the trust the balls will get
            token = self._token = JobToken()
            self._job = Job("plan_layout", 0.0, f"planning {n} balls and the camera")
            th = threading.Thread(target=self._run, args=(args, basis, token), name="monotracker-layout", daemon=True)
            self._thread = th
        self._bus.event("layout_started", f"planning the fiducial layout: {n} balls"
                        + (" (quick)" if quick else ""), {"balls": n, "quick": bool(quick), "noise_px": noise})
        th.start()
        return CommandResult.done(f"planning {n} balls and the camera placement")

    def cancel(self, reason: str = "cancelled by the operator") -> CommandResult:
        """Stop the running plan at its next step; the previous result (if any) stays.
        Refuses (ok=False): no layout is being planned."""
        with self._lock:
            token, job = self._token, self._job
            if token is None or job is None or job.done or not token.cancel(reason):
                return CommandResult.refused("no layout is being planned")
            self._job = Job(job.name, job.progress, "layout planning stopped", reason, True)
        self._bus.event("layout_stopped", f"layout planning stopped: {reason}", {"reason": reason})
        return CommandResult.done("layout planning stopped; the previous layout (if any) is unchanged")

    def wait(self, timeout: float | None = None) -> Job | None:
        """Block until the current plan ends (s; None = no limit; for scripts and tests, the UI
        polls snapshots). The last :class:`Job`, or None when none ever ran."""
        th = self._thread
        if th is not None:
            th.join(timeout)
        with self._lock:
            return self._job

    # ------------------------------------------------------------------ snapshot
    def summary(self) -> LayoutSummary | None:
        """``snap.layout`` now (None until a plan was started); the caller holds the state lock."""
        job, res = self._job, self._result
        if job is None:
            return None
        if res is None:
            return LayoutSummary(job=job)
        stale = self._basis != self._basis_of(self._editor.plan, self._ct())
        return LayoutSummary(**{**res.__dict__, "job": job, "stale": stale})

    @staticmethod
    def _basis_of(plan, loaded) -> tuple:
        """What a layout depends on: the CT, the target and entry, the registration fiducials, the
        balls' finish the plan states (the trust it predicts)."""
        def pt(p):
            return None if p is None else tuple(np.round(np.asarray(p, float), 3))

        return (None if loaded is None else loaded.summary.path, id(None if loaded is None else loaded.head_mesh),
                pt(plan.target_lps_mm), pt(plan.entry_lps_mm),
                tuple((f.id, pt(f.centre_lps_mm)) for f in plan.registration_fiducials()), plan.ball_finish)

    # ------------------------------------------------------------------ the job's thread
    def _progress(self, token: JobToken):
        started = self._clock()

        def report(frac: float, msg: str) -> None:
            token.check()
            if self._clock() - started > self.time_limit_s:
                self.cancel(f"planning took longer than its {self.time_limit_s:.0f} s limit "
                            "(the computer is busy, or try a quick plan)")
                token.check()
            state = self._robot_state()
            if state in BUSY_ROBOT_STATES:
                self.cancel(f"the robot was {state}: layout planning runs only while it is disarmed")
                token.check()
            with self._lock:
                if token is self._token and not token.cancelled:
                    self._job = Job("plan_layout", 0.98 * float(frac), msg)
        return report

    def _run(self, args: dict, basis, token: JobToken) -> None:
        t0 = time.perf_counter()
        try:
            result = self._plan(args, token)
        except JobCancelled:
            return  # snap.layout.job already says why; the previous result stays
        except ValueError as exc:  # the planner's one-line refusals
            self._end(token, "layout not planned", str(exc))
            return
        except Exception as exc:  # report, never kill the engine
            log.exception("layout planning failed")
            self._end(token, "layout planning failed", f"internal error: {type(exc).__name__}: {exc}")
            self._bus.alert("warning", "layout_failed", f"layout planning failed: {type(exc).__name__}: {exc}")
            return
        elapsed = time.perf_counter() - t0
        with self._lock:
            if token.cancelled or token is not self._token:
                return
            token.committed = True
            self._result = LayoutSummary(job=Job("plan_layout", 1.0, "", None, True), elapsed_s=elapsed, **result)
            self._basis = basis
            s = result["suggestion"].worst_hidden
            line = (f"layout planned: {len(result['balls_lps_mm'])} balls, camera "
                    f"{result['camera_distance_mm']:.0f} mm away; predicted error at the target with the worst "
                    f"ball hidden: " + (f"p95 {s.p95_mm:.2f} mm, {100 * s.trusted:.0f} % trusted" if s else "no pose"))
            self._job = Job("plan_layout", 1.0, line, None, True)
        self._bus.event("layout_planned", line, {"balls_lps_mm": np.round(result["balls_lps_mm"], 2).tolist(),
                                                  "T_ct_cam": np.round(result["T_ct_cam"], 4).tolist(),
                                                  "balls_needed": result["balls_needed"],
                                                  "elapsed_s": round(elapsed, 1)})

    def _end(self, token: JobToken, message: str, error: str) -> None:
        with self._lock:
            if token.cancelled or token is not self._token:
                return
            self._job = Job("plan_layout", 1.0, message, error, True)

    def _plan(self, a: dict, token: JobToken) -> dict:
        """Build the problem and plan (on the job's thread); the snapshot fields of the result."""
        from monotracker.planning import HeadSurface, build_problem, plan_layout

        report = self._progress(token)
        report(0.0, "reading the head surface")
        head = HeadSurface.from_mesh(a["head_mesh"])
        problem = build_problem(head, a["target"], entry=a["entry"], existing=a["existing"],
                                radius_mm=a["radius_mm"], camera=a["camera"], noise_px=a["noise_px"])
        quick = a["quick"]
        plan = plan_layout(problem, a["n_balls"], progress=report, config=a["rules"], fiducial_ids=a["existing_ids"],
                           n_directions=QUICK_DIRECTIONS if quick else FULL_DIRECTIONS, refine=not quick)
        token.check()
        ids = a["existing_ids"]
        cam = a["camera"]
        return dict(
            balls_lps_mm=frozen_array(plan.balls),
            from_fiducial=tuple(int(ids[i]) if i >= 0 else -1 for i in plan.from_existing),
            T_ct_cam=frozen_array(plan.T_ct_cam), camera_distance_mm=float(plan.camera.distance_mm),
            K=frozen_array(cam.K), image_size=tuple(int(v) for v in cam.image_size),
            suggestion=expectation(plan.expected), current=expectation(plan.existing_here),
            current_best=expectation(plan.existing_best), balls_needed=plan.balls_needed,
            notes=tuple(plan.notes), candidates_lps_mm=frozen_array(plan.candidates.centres),
            error_map_mm=frozen_array(plan.error_map_mm), target_lps_mm=frozen_array(a["target"]),
            noise_px=float(a["noise_px"]), radius_mm=float(a["radius_mm"]),
        )
