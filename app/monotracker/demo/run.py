"""The headless digital-twin demo: the whole loop on the sample CT, simulated camera and arm.

``run_demo(DemoOptions(...)) -> dict`` drives a :class:`~monotracker.engine.Session` exactly as
the web app does (load the sample CT, confirm the detected fiducials, the sample plan, start the
camera, arm with the PIN, start tracking), on a **simulated clock** (``clock="sim"``): camera,
registration and control run in lock-step at their own rates, and every pose becomes available
only after the camera's 30 ms transport delay plus the *measured* compute time (CPU time of the
thread) of its detection + registration, so accuracy, pose age and latency are what this machine's
code delivers, independent of how loaded the machine is. Whether the run
kept up with real time is reported separately (``realtime_factor`` = simulated s / wall s).

Measured against the simulator's truth:

* registration TRE at the planned target (mm): ``|T_cam_ct_est @ target - T_cam_ct_true @ target|``
  for every trusted pose;
* needle tip error to the planned entry (mm) and axis angle error (deg) on every control tick
  while the robot state is ``tracking``, from the arm's true tip pose and the head's TRUE pose,
  after the first ``settle_s`` seconds of tracking (the initial approach is excluded);
* capture -> command latency (ms);
* for a fault injected at ``fault_at_s``: when the engine detected it (first alert after the
  fault), when the arm came to a standstill (tip speed < 0.5 mm/s and all joints < 1e-3 rad/s,
  and staying so for 0.2 s), how far the needle tip travelled after the fault, what the engine
  reported, and whether the saved plan is unchanged.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monotracker.engine.config import FAULTS, TRAJECTORIES, SessionConfig
from monotracker.engine.session import Session
from monotracker.errors import InputError, MonoTrackerError
from monotracker.geometry import apply_transform

STANDSTILL_TIP_MM_S = 0.5
STANDSTILL_JOINT_RAD_S = 1e-3
STANDSTILL_HOLD_S = 0.2
#: alert codes that count as "the engine noticed" each fault
FAULT_CODES = {
    "camera-freeze": ("camera_freeze", "pose_stale"),
    "occlude-all": ("occlusion", "pose_lost", "pose_stale"),
    "robot-disconnect": ("robot_disconnected",),
    "bad-pose": ("pose_jump", "bad_pose"),
    "camera-bump": ("camera_moved",),
    "camera-sag": ("camera_moved",),
}


@dataclass
class DemoOptions:
    seconds: float = 10.0
    trajectory: str = "breathing"
    fault: str = "none"
    fault_at_s: float | None = None  # default: half-way through the tracking time
    #: move the fault to where the true head moves fastest (at the planned entry) within this
    #: many seconds after ``fault_at_s``: the arm is then surely moving when it hits, whatever
    #: the machine's load did to when tracking started (tests of stopping need that)
    fault_at_fastest_within_s: float | None = None
    seed: int = 0
    camera_fps: float = 30.0
    control_hz: float = 125.0
    settle_s: float = 2.0
    home: Path | None = None
    pin: str = "1234"
    record: Path | None = None  # record the session into this folder (monotracker.engine.recording)
    igtl_port: int | None = None  # stream to OpenIGTLink clients on this port (monotracker.interop.igtl)
    allow_remote: bool = False  # OpenIGTLink on every interface, not only 127.0.0.1
    #: SessionConfig fields to override (e.g. the benchmark's "no gate" baseline)
    config_overrides: dict = field(default_factory=dict)

    def validate(self) -> None:
        if not (self.seconds > 0):
            raise InputError("--seconds must be positive")
        if not (self.trajectory in TRAJECTORIES or hasattr(self.trajectory, "pose")):
            raise InputError(f"unknown trajectory {self.trajectory!r}; use one of {', '.join(TRAJECTORIES)}")
        if self.fault_at_fastest_within_s is not None and not (self.fault_at_fastest_within_s >= 0):
            raise InputError("fault_at_fastest_within_s must be >= 0 s")
        if self.fault not in FAULTS:
            raise InputError(f"unknown fault {self.fault!r}; use one of {', '.join(FAULTS)}")


def _stats(x) -> dict | None:
    a = np.asarray(x, float)
    if a.size == 0:
        return None
    return {"mean": float(a.mean()), "rms": float(np.sqrt(np.mean(a ** 2))), "p95": float(np.percentile(a, 95)),
            "max": float(a.max()), "n": int(a.size)}


class _Recorder:
    """Per-tick truth metrics (a tick listener on the session)."""

    def __init__(self, session: Session):
        self.s = session
        plan = session.plan_copy()
        self.entry, self.target = plan.entry_lps_mm, plan.target_lps_mm
        self.rows = []  # (t, state, tip_err, ang_err, tip_speed, max_joint_speed)
        self.tip_positions = []  # (t, tip position in base mm) 
        self.tre = []
        self.tip_vs_registered = []  # (t, tip distance to the registered entry mm) while tracking
        self._reg_error = None
        self._seen_pose = None
        self.tracking_since = None
        self.stages = []   # per estimate: vision's stage times (s) + the pipeline's CPU time (s)
        self.pose_age = []  # (t, age of the newest trusted pose, s) on every tick
        self._trusted_capture = None

    def __call__(self, t: float) -> None:
        from monotracker.robot.targets import tip_and_axis_error

        s = self.s
        T_base_ct = s.truth_T_base_ct(t)
        st = s.robot_status()
        tip = ang = None
        if st is not None and st.T_base_tip is not None and T_base_ct is not None:
            tip, ang = tip_and_axis_error(st.T_base_tip, T_base_ct, self.entry, self.target)
        state = st.state if st is not None else "disarmed"
        if state == "tracking" and self.tracking_since is None:
            self.tracking_since = t
        qd = 0.0 if st is None or st.qd is None else float(np.max(np.abs(st.qd)))
        self.rows.append((t, state, tip, ang, 0.0 if st is None else float(st.speed_mm_s), qd))
        if (state == "tracking" and st is not None and st.T_base_tip is not None and T_base_ct is not None
                and self._reg_error is not None):
            # the entry where the newest registration puts it, on the head as it is now: what a
            # tracker without latency would reach with this registration
            e = apply_transform(T_base_ct @ self._reg_error, self.entry)
            self.tip_vs_registered.append((t, float(np.linalg.norm(st.T_base_tip[:3, 3] - e))))
        if st is not None and st.T_base_tip is not None:
            self.tip_positions.append((t, st.T_base_tip[:3, 3].copy()))
        if self._trusted_capture is not None:
            self.pose_age.append((t, t - self._trusted_capture))
        rec = s.latest_pose()
        if rec is not None and rec.sample is not self._seen_pose:
            self._seen_pose = rec.sample
            smp = rec.sample
            st = dict(getattr(smp.raw, "stages_s", None) or {})
            st.update({k: v for k, v in (smp.stages or {}).items() if k in ("pipeline_s", "after_pose_s")})
            self.stages.append(st)
            if rec.trusted:
                self._trusted_capture = smp.t_capture
            if rec.trusted and smp.T_cam_ct is not None and smp.truth_T_cam_ct is not None:
                d = apply_transform(smp.T_cam_ct, self.target) - apply_transform(smp.truth_T_cam_ct, self.target)
                # the registration's error as a rigid map in CT (T_cam_ct = truth @ error)
                self._reg_error = np.linalg.solve(smp.truth_T_cam_ct, smp.T_cam_ct)
                self.tre.append(float(np.linalg.norm(d)))


#: the per-frame stages of detection + registration + screening + gates (vision's PoseEstimate.stages_s)
DETECT_REGISTER_STAGES = ("hint", "detect", "register", "screen", "gates")


def _pipeline_figures(stages: list[dict]) -> dict:
    """``detect_register_ms_median`` (detection + registration + screening + gates per frame, ms,
    wall time of the stages), ``pipeline_ms`` (the whole estimate's CPU time per frame, with the
    camera-motion watch and the validation check: what the simulated clock charges, ms),
    ``after_pose_ms`` (the work after each pose was given out, charged to the estimator: a due
    frame's camera-motion check, a few us on the other frames) and
    ``stages_ms`` (median per stage, ms)."""
    def pct(a):
        a = np.asarray(a, float) * 1000
        a = a[np.isfinite(a)]
        return None if a.size == 0 else {"p50": float(np.median(a)), "p95": float(np.percentile(a, 95)),
                                          "p99": float(np.percentile(a, 99)), "n": int(a.size)}
    dr = [sum(s.get(k, 0.0) for k in DETECT_REGISTER_STAGES) for s in stages if "detect" in s]
    keys = sorted({k for s in stages for k in s if k not in ("pipeline_s", "after_pose_s")})
    return {"detect_register_ms_median": float(np.median(dr)) * 1000 if dr else None,
            "detect_register_ms": pct(dr),
            "pipeline_ms": pct([s["pipeline_s"] for s in stages if "pipeline_s" in s]),
            "after_pose_ms": pct([s["after_pose_s"] for s in stages if "after_pose_s" in s]),
            "stages_ms": {k: float(np.nanmedian([s.get(k, np.nan) for s in stages])) * 1000 for k in keys}}


def _standstill_after(rows, t0: float) -> float | None:
    """First time >= t0 from which the arm stays still for STANDSTILL_HOLD_S."""
    start = None
    for t, _state, _tip, _ang, v, qd in rows:
        if t < t0:
            continue
        still = v < STANDSTILL_TIP_MM_S and qd < STANDSTILL_JOINT_RAD_S
        if still:
            if start is None:
                start = t
            if t - start >= STANDSTILL_HOLD_S:
                return start
        else:
            start = None
    return None


def _fastest_head_time(s: Session, t0: float, window_s: float, rate_hz: float) -> float:
    """The control tick in ``[t0, t0 + window_s]`` where the simulator's TRUE planned entry
    point moves fastest (s, session clock); ``t0`` when the rig has no truth."""
    if s.truth_T_base_ct(t0) is None:
        return t0
    entry = s.plan_copy().entry_lps_mm
    ts = t0 + np.arange(0.0, window_s + 1e-9, 1.0 / rate_hz)
    p = np.array([apply_transform(s.truth_T_base_ct(t), entry) for t in ts])
    if len(p) < 2:
        return t0
    return float(ts[1:][int(np.argmax(np.linalg.norm(np.diff(p, axis=0), axis=1)))])


def run_demo(opts: DemoOptions, camera_factory=None, robot_factory=None, on_tracking=None) -> dict:
    """Run the twin and return the summary dict (see the module docstring).

    ``on_tracking(session)`` is called once tracking has started (used by the crash test)."""
    opts.validate()
    wall0 = time.perf_counter()
    cpu0 = time.process_time()
    tmp = None
    home = opts.home
    if home is None:
        tmp = tempfile.TemporaryDirectory(prefix="monotracker-demo-")
        home = Path(tmp.name)
    kw = dict(home=Path(home), camera="sim", trajectory=opts.trajectory, robot="sim", arm_pin=opts.pin,
              clock="sim", camera_fps=opts.camera_fps, control_hz=opts.control_hz, seed=opts.seed)
    kw.update(opts.config_overrides)  # e.g. camera="sim-points", or the benchmark's "no gate" baseline
    cfg = SessionConfig(**kw)
    s = Session(cfg, camera_factory=camera_factory, robot_factory=robot_factory)
    streamer = None
    try:
        if opts.igtl_port is not None:
            from monotracker.interop.igtl import IGTLStreamer

            streamer = IGTLStreamer(s, opts.igtl_port, opts.allow_remote).start()
        out = _run(s, opts, wall0, cpu0, on_tracking)
        if streamer is not None:
            out["igtl"] = {"host": streamer.host, "port": streamer.port, "sent": dict(streamer.sent),
                           "epoch0": streamer.epoch0}
        return out
    finally:
        if streamer is not None:
            streamer.stop()
        s.shutdown()
        if tmp is not None:
            tmp.cleanup()


def _run(s: Session, opts: DemoOptions, wall0: float, cpu0: float, on_tracking) -> dict:
    setup_steps = []
    plan = s.plan_copy()
    if not (plan.fiducials_locked and plan.path_complete):
        r = s.load_sample_ct()
        if not r.ok:
            raise MonoTrackerError(r.message)
        job = s.wait_for_job(120)
        if job is None or job.error:
            raise MonoTrackerError(f"sample CT failed: {None if job is None else job.error}")
        for f in s.snapshot().fiducials:
            s.set_fiducial_status(f.id, "confirmed")
        r = s.confirm_fiducials()
        if not r.ok:
            raise MonoTrackerError(f"fiducials: {r.message}")
        r = s.use_sample_plan()
        if not r.ok:
            raise MonoTrackerError(f"plan: {r.message}")
        setup_steps.append("sample CT loaded, detected fiducials confirmed, sample plan set")
    else:
        setup_steps.append("saved plan restored")
        if plan.ct_path:  # arming checks the path against the plan's CT: reload it
            r = s.load_ct(plan.ct_path)
            job = s.wait_for_job(120) if r.ok else None
            if not r.ok or job is None or job.error:
                raise MonoTrackerError(f"the plan's CT: {r.message if not r.ok else (job.error if job else 'no job')}")
    if opts.record is not None:
        r = s.start_recording(opts.record)
        if not r.ok:
            raise MonoTrackerError(f"--record: {r.message}")
    r = s.start_camera()
    if not r.ok:
        raise MonoTrackerError(f"camera: {r.message}")
    wall_loop0, t_loop0 = time.perf_counter(), s.snapshot().t
    rec = _Recorder(s)
    s.add_tick_listener(rec)
    # acquire a trusted pose (at most 5 s of simulated time)
    t_acq = None
    for _ in range(100):
        s.advance(0.05)
        p = s.snapshot().pose
        if p is not None and p.trusted:
            t_acq = s.snapshot().t
            break
    if t_acq is None:
        p = s.snapshot().pose
        raise MonoTrackerError(f"no trusted pose within 5 s ({'no estimate' if p is None else p.reason})")
    r = s.arm(opts.pin)
    if not r.ok:
        raise MonoTrackerError(f"arm: {r.message}")
    r = s.start_tracking()
    if not r.ok:
        raise MonoTrackerError(f"start tracking: {r.message}")
    t_track = s.snapshot().t
    if on_tracking is not None:
        on_tracking(s)
    plan_before = s.plan_copy().to_dict()
    t_end = t_track + opts.seconds
    fault_at = None
    if opts.fault != "none":
        fault_at = t_track + (opts.fault_at_s if opts.fault_at_s is not None else max(opts.settle_s + 1.0, 0.5 * opts.seconds))
        if opts.fault_at_fastest_within_s:
            fault_at = _fastest_head_time(s, fault_at, float(opts.fault_at_fastest_within_s), opts.control_hz)
        fault_at = min(fault_at, t_end - 0.5)
        s.advance(max(0.0, fault_at - s.snapshot().t))
        fault_at = s.snapshot().t
        r = s.inject_fault(opts.fault)
        if not r.ok:
            raise MonoTrackerError(f"fault injection: {r.message}")
    s.advance(max(0.0, t_end - s.snapshot().t))
    recording = None
    if opts.record is not None:
        r = s.stop_recording()
        recording = {"path": str(opts.record), "ok": r.ok, "message": r.message}
    wall = time.perf_counter() - wall0
    wall_loop = time.perf_counter() - wall_loop0
    cpu = time.process_time() - cpu0
    snap = s.snapshot()
    # ---------------------------------------------------------------- summarise
    settle_from = t_track + opts.settle_s
    until = fault_at if fault_at is not None else float("inf")
    until = min(until, t_end + 1e-9)
    trk = [r for r in rec.rows if r[1] == "tracking" and settle_from <= r[0] < until and r[2] is not None]
    alerts = [e for e in s.audit_entries() if e.kind == "alert" and e.session_id == s.session_id]
    frames = snap.camera.frames
    sim_s = snap.t
    lat = np.array(s.latencies_s()) * 1000
    out = {
        "trajectory": opts.trajectory if isinstance(opts.trajectory, str) else repr(opts.trajectory),
        "fault": opts.fault,
        "seconds_tracking": opts.seconds,
        "simulated_s": sim_s,
        "wall_s": wall,
        "cpu_s": cpu,
        "loop_wall_s": wall_loop,
        "realtime_factor": (sim_s - t_loop0) / wall_loop if wall_loop > 0 else None,
        "clock": "simulated, lock-step; a pose is available 30 ms (camera) + its measured CPU time after capture",
        "cpus_available": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "frames": frames,
        "fps": frames / sim_s if sim_s > 0 else 0.0,
        "fps_wall": frames / wall_loop if wall_loop > 0 else 0.0,
        "setup": setup_steps,
        "time_to_first_pose_s": t_acq,
        "tracking_started_at_s": t_track,
        "registration_tre_mm": _stats(rec.tre),
        "tip_error_mm": _stats([r[2] for r in trk]),
        # against the entry where the newest registration puts it on the head as it is now (not
        # the truth): the tracking part of the error, without the registration's own
        "tip_error_vs_registered_mm": _stats([e for t, e in rec.tip_vs_registered if settle_from <= t < until]),
        "axis_error_deg": _stats([r[3] for r in trk]),
        "tracking_fraction": len(trk) / max(1, len([r for r in rec.rows if settle_from <= r[0] < until])),
        # after the first lock (tracking started), until the fault
        "tracking_fraction_after_lock": (len([r for r in rec.rows if r[1] == "tracking" and t_track <= r[0] < until])
                                         / max(1, len([r for r in rec.rows if t_track <= r[0] < until]))),
        "latency_ms": _stats(lat),
        # age of the newest trusted pose on every control tick after settling (ms)
        "pose_age_ms": _stats([1000 * a for t, a in rec.pose_age if settle_from <= t < until]),
        **_pipeline_figures(rec.stages),
        "final_state": snap.robot.state,
        "recording": recording,
        "alerts": [{"t": round(a.t_session, 3), "level": a.level, "code": a.code, "message": a.message}
                   for a in alerts],
    }
    if fault_at is not None:
        codes = FAULT_CODES[opts.fault]
        det = next((a for a in alerts if a.t_session >= fault_at - 1e-9 and a.code in codes), None)
        t_det = det.t_session if det is not None else None
        t_still = _standstill_after(rec.rows, fault_at)
        after = [p for t, p in rec.tip_positions if t >= fault_at]
        travel = max(float(np.linalg.norm(p - after[0])) for p in after) if after else None
        after_det = [p for t, p in rec.tip_positions if t_det is not None and t >= t_det]
        travel_det = max(float(np.linalg.norm(p - after_det[0])) for p in after_det) if after_det else None
        v_fault = max((r[4] for r in rec.rows if fault_at - 0.1 <= r[0] <= fault_at), default=None)
        response = _arm_response_s(s)
        out["fault_report"] = {
            "injected_at_s": fault_at,
            "detected_at_s": t_det,
            "detection_delay_s": None if t_det is None else t_det - fault_at,
            "standstill_at_s": t_still,
            "standstill_after_fault_s": None if t_still is None else t_still - fault_at,
            "standstill_after_detection_s": None if (t_still is None or t_det is None) else max(0.0, t_still - t_det),
            "engine_reported": None if det is None else f"[{det.level}] {det.code}: {det.message}",
            "arm_travel_after_fault_mm": travel,
            # from the detection on: what the stop itself cost (before it the arm follows the head)
            "arm_travel_after_detection_mm": travel_det,
            "tip_speed_before_fault_mm_s": v_fault,
            # the arm's own response to a stop (simulated UR10: command delay + velocity lag, s)
            "arm_response_s": response,
            # the physics: an arm following the head at v_fault cannot know of the fault before
            # the detection, and a stop reaches the tip only after the arm's response (a
            # first-order lag runs on v x tau); a stop that adds nothing of its own travels about this
            "travel_physics_mm": (None if None in (v_fault, response, t_det)
                                else v_fault * (t_det - fault_at + response)),
            "state_after": snap.robot.state,
            "plan_intact": s.plan_copy().to_dict() == plan_before,
        }
    return out


def _arm_response_s(s: Session) -> float | None:
    """Command delay + velocity lag of the simulated arm (s); None for any other backend."""
    st = s.robot_status()
    return None if st is None else st.response_s


def format_report(r: dict) -> str:
    """Human-readable summary of :func:`run_demo`'s result."""

    def st(d, unit, nd=2):
        if not d:
            return "n/a"
        return f"mean {d['mean']:.{nd}f} / p95 {d['p95']:.{nd}f} / max {d['max']:.{nd}f} {unit}"

    lines = [
        f"MonoTracker headless demo: trajectory={r['trajectory']} fault={r['fault']} "
        f"tracking {r['seconds_tracking']:.1f} s",
        f"  clock               : {r['clock']}",
        f"  simulated / wall    : loop {r['simulated_s']:.2f} s in {r['loop_wall_s']:.2f} s (real-time factor "
        f"{r['realtime_factor']:.2f}x on {r['cpus_available']} CPU(s); "
        + ("kept up with real time)" if r['realtime_factor'] >= 1 else "SLOWER than real time)")
        + f"; whole run incl. CT load {r['wall_s']:.2f} s",
        f"  frames              : {r['frames']}  ({r['fps']:.1f} fps simulated, {r['fps_wall']:.1f} fps wall)",
        f"  registration TRE    : {st(r['registration_tre_mm'], 'mm')} at the target vs truth",
        f"  needle tip error    : {st(r['tip_error_mm'], 'mm')} to the planned entry (tracking, after settling)",
        f"  needle axis error   : {st(r['axis_error_deg'], 'deg')}",
        f"  latency             : {st(r['latency_ms'], 'ms', 1)} capture -> command",
        f"  pose pipeline       : detection + registration {r['detect_register_ms_median'] or float('nan'):.1f} ms "
        f"median per frame; tracking {100 * r['tracking_fraction']:.1f} % of the time after settling",
        f"  final robot state   : {r['final_state']}",
    ] + ([f"  recording           : {r['recording']['message']} ({r['recording']['path']})"]
         if r.get("recording") else []) + [
        f"  alerts ({len(r['alerts'])})" + (":" if r["alerts"] else ""),
    ]
    for a in r["alerts"][:20]:
        lines.append(f"    t={a['t']:7.3f}s [{a['level']}] {a['code']}: {a['message']}")
    if len(r["alerts"]) > 20:
        lines.append(f"    ... {len(r['alerts']) - 20} more")
    fr = r.get("fault_report")
    if fr:
        def ms(v):
            return "never" if v is None else f"{1000 * v:.0f} ms"

        def _mm(v, nd=2):
            return "n/a" if v is None else f"{v:.{nd}f} mm"
        lines += [
            f"  fault {r['fault']} at t={fr['injected_at_s']:.3f}s:",
            f"    detected after    : {ms(fr['detection_delay_s'])}",
            f"    arm standstill    : {ms(fr['standstill_after_detection_s'])} after detection, "
            f"{ms(fr['standstill_after_fault_s'])} after the fault",
            f"    engine reported   : {fr['engine_reported']}",
            f"    tip travel        : {_mm(fr['arm_travel_after_fault_mm'])} after the fault, "
            f"{_mm(fr['arm_travel_after_detection_mm'])} after detection (tip at {_mm(fr['tip_speed_before_fault_mm_s'], 1)}/s "
            f"before it; physics {_mm(fr['travel_physics_mm'])}: that speed x (detection + the arm's response "
            f"{ms(fr['arm_response_s'])}))",
            f"    state after       : {fr['state_after']}; plan intact: {fr['plan_intact']}",
        ]
    return "\n".join(lines)


def report_json(r: dict) -> str:
    return json.dumps(r, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))


__all__ = ["DemoOptions", "run_demo", "format_report", "report_json"]
