"""The tracking loop's core: camera -> pose -> trust verdict -> needle target -> tracker -> arm.

The core holds the pose side (the newest estimate and its verdict, holds and resumes, the needle
target, listeners) and composes its parts, each in its own module: :class:`~.camera.CameraControl`
(the camera rig, its frames and faults), :class:`~.robot.RobotControl` (the robot rig, arming and
tracking), the clock that drives it (:class:`~.clocks.SimStepper` or :class:`~.clocks.RealThread`)
and the read side (:mod:`.summaries`).

Rates and threads (clock="real", the web app):

* camera + registration: the vision pose stream's own thread (``PoseStream``), at camera rate or
  as fast as registration allows (it always works on the newest frame, dropping older ones);
* control: the robot ``Tracker``'s real-time thread at ``control_hz``;
* the engine thread (``monotracker-loop``, 250 Hz) moves the freshest pose into the tracker and
  runs the watchdogs: the camera's frames (``camera_freeze``: repeated bit for bit;
  ``camera_late``: no new frame for ``freeze_after_s``; ``camera_stalled``: none for
  ``stall_after_s``), stale pose (freshest trusted pose older than ``max_pose_age_s``), robot
  connection and state changes.

clock="sim" (demo, tests, benchmark): no threads. :meth:`TrackingLoop.advance` steps a simulated
clock at the control period; a frame is captured every camera period when the estimator is free,
estimated synchronously, and its result becomes available ``d + w`` seconds after capture, where
``d`` is the camera's transport delay (exposure + readout + USB transfer; ``rig.transport_delay_s``,
30 ms for the simulated camera) and ``w`` is the *measured compute time* of detection + registration
(CPU time of the engine thread, ``time.thread_time()``: on a shared, overloaded machine wall time
would mostly measure the other processes) (so slow registration shows up honestly
as pose age and latency, and frames arriving while it is busy are dropped as in the threaded
pose stream). The same gate/target/watchdog code runs in both modes.

Latency ("capture -> command"): the time from a frame's capture to the first control command
computed from the target derived from it (``t_command - t_capture``), reported per command.

Holding: when the pose is not trusted or too old, the tracker gets ``valid=False`` and holds the
arm still (``Tracker.set_target(..., valid=False)``); it resumes by itself when a trusted pose
returns. Every transition is an alert.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from monotracker.engine import rigs
from monotracker.engine.alarms import (CATALOGUE, FRESHNESS_CODES, POSE_CODES, SET_ASIDE_SHARE, SET_ASIDE_WINDOW_S,
                                       VERDICT_CODES, level_of)
from monotracker.engine.loop import summaries as _summaries
from monotracker.engine.loop.camera import CameraControl
from monotracker.engine.loop.clocks import RealThread, SimStepper
from monotracker.engine.loop.gate import PoseGate
from monotracker.engine.loop.load import PipelineLoad
from monotracker.engine.loop.robot import RobotControl

log = logging.getLogger(__name__)
#: the holds about the camera's frames (:meth:`CameraControl.frame_condition`)
FRAME_CODES = ("camera_freeze", "camera_stalled", "camera_late")


@dataclass(frozen=True)
class PoseRecord:
    """The newest estimate the loop handled and its trust verdict: ``sample`` (:class:`PoseSample`,
    mm, session s), ``trusted``, ``code`` (the verdict's code, "ok" when trusted), ``reason``."""

    sample: rigs.PoseSample
    trusted: bool
    code: str
    reason: str


class TrackingLoop:
    """Owns the camera rig, the trust verdict, the tracker and the arm of one session, through its
    parts (see the module docstring).

    Collaborators: ``config`` (:class:`~monotracker.engine.config.SessionConfig`), ``clock`` (the
    session clock, s), ``events`` (the event bus: decisions and state changes), ``alarms``
    (:class:`~monotracker.engine.alarms.Alarms`), ``plan`` (the plan editor: the plan, its
    readiness, the camera and hand-eye it stores), ``access`` (the PIN guard arming checks) and
    ``session``, the session the rigs report to (``engine/rigs/factory.py``)."""

    def __init__(self, *, config, clock, events, alarms, plan, access, session):
        cfg = config
        self.cfg = cfg
        self.clock = clock
        self.events = events
        self.alarms = alarms
        self.plan = plan
        self._lock = threading.RLock()
        self.gate = PoseGate.from_config(cfg)
        self._latest: PoseRecord | None = None
        self._last_trusted: rigs.PoseSample | None = None
        self._holding_reason: str | None = None  # why the loop currently holds (None = not holding)
        self._holding_code: str | None = None
        self._hold_reported = False  # the current hold episode was reported (so its end is too)
        self._fresh_since: float | None = None  # trusted poses arriving fresh without a gap since (s)
        self._dwell_s = cfg.resume_dwell_s  # current resume dwell (doubles while the stream keeps failing)
        self._fresh_resumed_at = -np.inf  # when tracking last resumed after a freshness hold
        self._hold_began = -np.inf  # when the current hold's cause was set
        self._latest_arrival = -np.inf  # when the newest estimate reached the loop
        self._seen_ids: set | None = None  # fiducial ids seen in the previous estimate
        #: (session s, {fiducial id: px}) of the estimates of the last SET_ASIDE_WINDOW_S, and when
        #: that record began (s): the condition fiducial_set_aside_long
        self._aside_log: deque = deque()
        self._aside_log_start = self.now()
        self._alerted: set[str] = set()
        self._target_T: np.ndarray | None = None
        self._target_stamp: float | None = None
        self._pending_latency_stamp: float | None = None
        self._pending_latency_set_at = 0.0
        self.latencies_s: deque[float] = deque(maxlen=5000)
        #: is the pose pipeline keeping up with the camera (``pipeline_overloaded``)
        self.load = PipelineLoad()
        self.last_command_t: float | None = None  # session time (s) of the newest latency measured
        self._tick_hooks: list = []
        self._pose_hooks: list = []
        self.camera = CameraControl(self, plan=plan, session=session)
        self.robot = RobotControl(self, plan=plan, access=access, session=session)
        self.driver = SimStepper(self) if cfg.clock == "sim" else RealThread(self)

    # ================================================================== plumbing
    def now(self) -> float:
        """Session clock, s."""
        return float(self.clock())

    def mark(self, key: str) -> bool:
        """True the first time ``key`` is raised in this episode (thread-safe)."""
        with self._lock:
            if key in self._alerted:
                return False
            self._alerted.add(key)
            return True

    def alert_once(self, key: str, level: str, code: str, message: str, data: dict | None = None) -> None:
        """Raise the alert once per episode of ``key`` (until :meth:`clear_alert` or a resume)."""
        if self.mark(key):
            self.alarms.alert(level, code, message, data)

    def clear_alert(self, key: str) -> bool:
        with self._lock:
            if key in self._alerted:
                self._alerted.discard(key)
                return True
            return False

    def add_tick_hook(self, fn) -> "callable":
        """``fn(t)`` after every control tick (clock="sim"; session s): metrics for the demo and
        benchmarks. Returns the function that removes the hook."""
        with self._lock:
            self._tick_hooks = self._tick_hooks + [fn]

        def remove() -> None:
            with self._lock:
                self._tick_hooks = [h for h in self._tick_hooks if h is not fn]
        return remove

    def run_tick_hooks(self, t: float) -> None:
        for fn in self._tick_hooks:
            fn(t)

    def add_pose_hook(self, fn) -> "callable":
        """``fn(sample, trusted, now)`` after every estimate the loop handles (both clocks, on the
        engine thread: keep it short, hand heavy work to your own thread; ``now`` session s). A
        hook that raises is logged and never disturbs the loop. Returns the function that removes
        the hook."""
        with self._lock:
            self._pose_hooks = self._pose_hooks + [fn]

        def remove() -> None:
            with self._lock:
                self._pose_hooks = [h for h in self._pose_hooks if h is not fn]
        return remove

    def _run_pose_hooks(self, sample, trusted: bool, now: float) -> None:
        for fn in self._pose_hooks:
            try:
                fn(sample, trusted, now)
            except Exception:  # recording/streaming must never hold the arm
                log.exception("pose hook failed")

    @property
    def holding_code(self) -> str | None:
        """Why the arm holds now (a catalogue code), or None."""
        with self._lock:
            return self._holding_code

    def holding_state(self) -> tuple[str | None, str | None]:
        """``(code, reason)`` of the current hold, or ``(None, None)``."""
        with self._lock:
            return self._holding_code, self._holding_reason

    @property
    def last_trusted(self) -> rigs.PoseSample | None:
        """The newest trusted estimate (None since the pose was last cleared)."""
        return self._last_trusted

    @property
    def holding_reason(self) -> str | None:
        """The hold's reason (one line), or None."""
        with self._lock:
            return self._holding_reason

    @property
    def latest(self) -> PoseRecord | None:
        """The newest estimate the loop handled, with its verdict (None: none since the pose was
        last cleared)."""
        return self._latest

    def target(self) -> tuple:
        """(T_base_target 4x4 mm or None, its capture stamp or None): the needle target last handed
        to the tracker."""
        with self._lock:
            return self._target_T, self._target_stamp

    # ================================================================== the loop proper
    def _fiducial_changes(self, sample: rigs.PoseSample) -> None:
        """Info alerts when fiducials vanish from / come back into the camera's view, and when
        one is newly set aside (found, but left out of the pose: the others disagree with it)."""
        aside = dict(getattr(sample, "set_aside", None) or {})
        with self._lock:       # the previous estimate's, from the window's record
            before = set(self._aside_log[-1][1]) if self._aside_log else set()
        new = sorted(set(aside) - before)
        if new:
            used = [fid for fid, st in sample.fiducial_status.items() if st == "seen" and fid not in aside]
            self.alarms.alert("info", "fiducials_set_aside", "; ".join(
                f"fiducial {fid} set aside: found {aside[fid]:.1f} px from where the others put it (partly hidden "
                "or off?)" for fid in new) + "; the pose comes from the others"
                + (f" ({len(used)} found)" if used else ""),
                {"set_aside": {fid: aside[fid] for fid in new}})
        self._aside_spell(aside)
        if not sample.fiducial_status:
            return
        seen = {fid for fid, st in sample.fiducial_status.items() if st == "seen"}
        prev, self._seen_ids = self._seen_ids, seen
        if prev is None:
            return
        lost, back = sorted(prev - seen), sorted(seen - prev)
        n, total = len(seen), len(sample.fiducial_status)
        verdict = ("tracking continues" if n >= self.cfg.min_fiducials
                   else f"fewer than {self.cfg.min_fiducials}: arm holds")
        if lost:
            self.alarms.alert("info", "fiducials_lost", f"fiducial{'s' if len(lost) > 1 else ''} "
                         f"{', '.join(map(str, lost))} out of view ({n} of {total} seen; {verdict})",
                         {"lost": lost, "seen": sorted(seen)})
        if back:
            self.alarms.alert("info", "fiducials_back", f"fiducial{'s' if len(back) > 1 else ''} "
                         f"{', '.join(map(str, back))} back in view ({n} of {total} seen)",
                         {"back": back, "seen": sorted(seen)})

    def _aside_spell(self, aside: dict) -> None:
        """The condition ``fiducial_set_aside_long``: a ball set aside (``aside``: fiducial id ->
        px from where the others put it, this estimate's) in at least ``SET_ASIDE_SHARE`` of the
        estimates of the last ``SET_ASIDE_WINDOW_S`` (the window full); reported once per episode."""
        now, code = self.now(), "fiducial_set_aside_long"
        with self._lock:             # invalidate_pose (another thread) clears the record
            log = self._aside_log
            log.append((now, dict(aside)))
            while log and log[0][0] < now - SET_ASIDE_WINDOW_S:
                log.popleft()
            full = self._aside_log_start <= now - SET_ASIDE_WINDOW_S
            counts: dict = {}
            for _t, ids in log:
                for fid in ids:
                    counts[fid] = counts.get(fid, 0) + 1
            long = sorted(fid for fid, c in counts.items() if full and c >= SET_ASIDE_SHARE * len(log))
            last = {fid: px for _t, ids in log for fid, px in ids.items()}   # the newest distance of each
        board = self.alarms.board
        if not long:
            board.clear(code, now)
            return
        msg = (f"fiducial{'s' if len(long) > 1 else ''} {', '.join(map(str, long))} left out of the pose in most "
               f"frames of the last {SET_ASIDE_WINDOW_S:g} s (found "
               + ", ".join(f"{last[fid]:.1f}" for fid in long) + " px from where the others put "
               f"{'them' if len(long) > 1 else 'it'}): {CATALOGUE[code].remedy}")
        if board.set(code, msg, now):
            self.alarms.alert("warning", code, msg, {"set_aside": {fid: last[fid] for fid in long}})

    def on_pose(self, sample: rigs.PoseSample, now: float) -> None:
        """A new estimate is available (engine thread / sim tick)."""
        rig = self.camera.rig
        stages = getattr(sample, "stages", None) or {}
        busy = stages.get("pipeline_s")   # the estimator's time per frame: the pose's, then what follows it
        if busy is not None:
            busy = float(busy) + float(stages.get("after_pose_s", 0.0))
        self.load.note_pose(sample.t_capture, sample.t_ready, now, getattr(rig, "transport_delay_s", 0.0), busy)
        self._fiducial_changes(sample)
        for fid, shift in getattr(sample, "moved", {}).items():
            self.alarms.persistent("fiducial_moved", f"fiducial {fid} moved about {shift:.1f} mm relative to the "
                         "others since the CT: excluded from registration (check it is firmly attached)",
                         {"fiducial": fid, "shift_mm": shift})
        v = self.gate.check_sample(sample)
        rec = PoseRecord(sample, v.trusted, v.code, v.reason)
        age = now - sample.t_capture
        limit = self.cfg.max_pose_age_s
        with self._lock:
            self._latest = rec
            self._latest_arrival = now
            if v.trusted:
                self._last_trusted = sample
            if not v.trusted or age > limit:
                self._fresh_since = None
            elif self._fresh_since is None:
                self._fresh_since = now
            fresh_for = None if self._fresh_since is None else now - self._fresh_since
            holding, code = self._holding_reason is not None, self._holding_code
        if v.trusted and age > limit:
            # trusted but already too old when it arrived: never a command; hold as stale
            self.hold(*self._stale(f"pose stale: trusted pose arrived {1000 * age:.0f} ms after capture "
                                   f"(limit {1000 * limit:.0f} ms)", now))
        elif v.trusted:
            dwell = self._dwell_s
            if holding and code in FRAME_CODES and self.camera.frame_condition(now):
                # a pose captured before the freeze (or gap), still in flight when it was detected:
                # the camera is still frozen, so it must not resume tracking (not even for a cycle),
                # and it does not count towards the fresh run the resume dwell asks for
                with self._lock:
                    self._fresh_since = None
                self._run_pose_hooks(sample, v.trusted, now)
                return
            if holding and code in FRESHNESS_CODES and fresh_for < dwell:
                # hysteresis: after a stale/frozen stream, resume only once poses have been
                # arriving fresh for resume_dwell_s (the arm keeps holding meanwhile); the pose
                # still goes to the pose hooks below: the recording must hold every estimate the
                # tracker made (its prior and noise estimate moved on with it), or a replay runs
                # another history
                with self._lock:
                    self._holding_reason = (f"pose stale: fresh again for {1000 * fresh_for:.0f} ms; resuming after "
                                            f"{1000 * dwell:.0f} ms")
            else:
                self.push_target(sample, now)
                if holding:
                    self.resume(f"pose trusted again ({sample.n_matched} fiducials)", self.registration_data(sample))
        else:
            self.hold(VERDICT_CODES.get(v.code, v.code), v.reason)
        self._run_pose_hooks(sample, v.trusted, now)

    def push_target(self, sample: rigs.PoseSample, now: float) -> None:
        plan = self.plan.copy()
        rob = self.robot.rig
        if not plan.path_complete or plan.T_base_cam is None or rob is None:
            return
        ref_R = None
        st = rob.status()
        if st.T_base_tip is not None:
            ref_R = st.T_base_tip[:3, :3]
        elif self._target_T is not None:
            ref_R = self._target_T[:3, :3]
        from monotracker.robot.targets import needle_target

        T = needle_target(plan.T_base_cam, sample.T_cam_ct, plan.entry_lps_mm, plan.target_lps_mm, ref_R)
        with self._lock:
            self._target_T, self._target_stamp = T, sample.t_capture
            self._pending_latency_stamp = sample.t_capture
            self._pending_latency_set_at = now
        rob.set_target(T, sample.t_capture, True, plan.T_base_cam @ sample.T_cam_ct)

    def hold(self, code: str, reason: str) -> None:
        """Make the tracker hold still (valid=False) and raise the alert once per episode.

        ``acquiring`` (waiting for the first consistent poses) is recorded as an event, not an alert."""
        rob = self.robot.rig
        if rob is not None:
            rob.set_target(self._target_T, self._target_stamp if self._target_stamp is not None else self.now(),
                                  False)
        with self._lock:
            self._holding_reason = reason
            if code == "acquiring" and self._holding_code not in (None, "acquiring"):
                return  # re-acquiring after an occlusion/fault: keep the cause for the resume alert
            if code in FRESHNESS_CODES and self._holding_code not in FRESHNESS_CODES:
                # a new stale episode: if the stream failed again soon after the last one, the
                # next resume waits twice as long (up to 4x); a quiet 10 s resets the dwell
                soon = self.now() - self._fresh_resumed_at < 10.0
                base = self.cfg.resume_dwell_s
                self._dwell_s = min(4 * base, 2 * self._dwell_s) if soon else base
            if code != self._holding_code:
                self._hold_began = self.now()
            self._holding_code = code
        tracking = self.robot.state() in ("tracking", "holding")
        msg = reason + ("; arm holding still" if tracking else "")
        report = self._set_pose_alarm(code, msg, tracking)
        if not self.mark(code) and not report:
            return  # this hold's condition again (a watchdog re-sets it every tick)
        self._hold_reported = self._hold_reported or report
        if not report:
            # a technical condition again within its quiet time (shown, counted, not re-reported),
            # inside its raise dwell (reported by the call that raises it), or the same episode
            # as the one before (its dwell kept it on the board)
            return
        unreported = self.alarms.board.unreported(code)
        if unreported:
            msg += f" ({unreported} more short episode{'s' if unreported > 1 else ''} since the last report)"
        if code == "acquiring":
            self.events.event("pose_acquiring", reason)
            return
        self.alarms.alert(level_of(code, "warning"), code, msg, {"reason": reason, "tracking": tracking,
                                                             "unreported_episodes": unreported})

    def _set_pose_alarm(self, code: str, message: str, tracking: bool) -> bool:
        """Show why the arm holds (one pose condition at a time); True when it is to be reported.
        A stopped camera is a condition only while the arm is armed; the rest always are (the
        registration view needs them too), as alarms while the arm follows the head."""
        board, now = self.alarms.board, self.now()
        if code == "camera_stopped" and self.robot.state() in ("disarmed", "estopped"):
            board.clear_all(POSE_CODES, now)
            return True
        if code != "engine_error":
            board.clear_all(POSE_CODES, now, keep=code)
        return board.set(code, message, now, level="alarm" if tracking else None)

    @staticmethod
    def registration_data(smp: rigs.PoseSample) -> dict:
        """What the audit log keeps about a registration (JSON-ready)."""
        return {"t_capture": smp.t_capture, "frame": smp.frame_index, "n_matched": smp.n_matched,
                "fre_mm": smp.fre_mm, "predicted_tre_mm": smp.predicted_tre_mm,
                "T_cam_ct_mm": None if smp.T_cam_ct is None else np.asarray(smp.T_cam_ct).tolist()}

    def resume(self, why: str, data: dict | None = None) -> None:
        with self._lock:
            was, code = self._holding_reason, self._holding_code
            self._holding_reason = self._holding_code = None
            if code in FRESHNESS_CODES:
                self._fresh_resumed_at = self.now()
            self._alerted &= {"robot_disconnected"}
            reported, self._hold_reported = self._hold_reported, False
        self.alarms.board.clear_all(tuple(c for c in POSE_CODES if c != "engine_error"), self.now())
        if was is None or not reported:
            return  # an unreported (rate-limited) hold ends unreported too
        if code == "acquiring":
            self.events.event("registration", f"registration acquired: {why}", data)
            return
        tracking = self.robot.state() in ("tracking", "holding")
        self.alarms.alert("info", "resumed", why + ("; tracking resumed" if tracking else ""),
                     {"after": was, "cause": code, "registration": data})

    def invalidate_pose(self, why: str, hold: bool = True) -> None:
        """Forget the pose: it no longer belongs to the current plan/camera (new CT, new plan,
        fiducials or path changed, camera stopped or failed). ``snap.pose`` becomes None, the trust
        gate starts over (first lock needs ``confirm_frames`` consistent estimates), and an engaged
        arm holds (``hold``) until a pose for *this* plan is trusted."""
        with self._lock:
            had = self._latest is not None
            self._latest = self._last_trusted = None
            self._fresh_since = None
            self._seen_ids = None
            self._aside_log.clear()
            self._aside_log_start = self.now()
            self.gate.reset()
        self.alarms.board.clear("fiducial_set_aside_long", self.now())
        if hold and self.robot.state() in ("tracking", "holding"):
            self.hold("pose_lost", f"pose cleared: {why}")
        if had:
            self.events.event("pose_invalidated", f"pose cleared: {why}", {"why": why})

    def restart_gate(self, about_ct) -> None:
        """A new camera: the trust verdict starts over, jumps measured at ``about_ct`` (CT mm)."""
        with self._lock:
            self.gate.reset()
            self.gate.set_anchor(about_ct)

    def fresh_pose(self, arrival_within_s: float | None = None):
        """``(record, now, None)`` when the newest pose is trusted and younger than max_pose_age_s
        (and, with ``arrival_within_s``, reached the loop at most that long ago, s); else
        ``(record, now, why)``. Inside the resume dwell after a stale episode a fresh pose is
        enough: the operator's Start confirms it (the dwell only keeps *automatic* resumes from
        flapping; the age limit is the same)."""
        rec, now = self._latest, self.now()
        with self._lock:
            code, reason = self._holding_code, self._holding_reason
            arrival = self._latest_arrival
            new_since_hold = arrival > self._hold_began
        if rec is None:
            return rec, now, "no pose yet"
        if not rec.trusted:
            return rec, now, rec.reason
        age = now - rec.sample.t_capture
        if code in FRESHNESS_CODES and not new_since_hold:
            return rec, now, reason or "pose is stale"  # no pose since the stream stalled
        if age > self.cfg.max_pose_age_s:
            return rec, now, (reason if code in FRESHNESS_CODES and reason else
                              f"pose is stale ({1000 * age:.0f} ms old)")
        if arrival_within_s is not None and now - arrival > arrival_within_s:
            return rec, now, (f"no pose for {1000 * (now - arrival):.0f} ms: the arm needs poses at most "
                              f"{1000 * 2 * arrival_within_s:.0f} ms apart")
        return rec, now, None

    def wait_for_fresh_pose(self, arrival_within_s: float | None = None):
        """Start tracking on a loaded machine: while trusted poses keep arriving (or the gate is
        confirming a new lock), a click that lands between two of them (or inside a short stale
        episode) waits for the next fresh one (arrived within ``arrival_within_s``, s, when
        given), up to ``start_wait_s`` (real clock only; the simulated clock cannot advance here)."""
        rec, now, why = self.fresh_pose(arrival_within_s)
        if why is None or self.cfg.clock != "real" or self.cfg.start_wait_s <= 0:
            return rec, now, why
        deadline = time.monotonic() + self.cfg.start_wait_s
        while (why is not None and time.monotonic() < deadline and rec is not None
               and (rec.trusted or rec.code == "acquiring")):  # poses flow (or are being confirmed)
            time.sleep(0.005 if arrival_within_s is not None else 0.01)
            rec, now, why = self.fresh_pose(arrival_within_s)
        return rec, now, why

    def watchdogs(self, now: float) -> None:
        """Camera frames (frozen, stalled, late), stale pose, robot state (every engine tick). A
        condition that holds is set again at every tick, so that a dwell row is raised once it
        stood its ``raise_after_s`` (the hold itself is immediate)."""
        cond = self.camera.frame_condition(now)
        if cond:
            with self._lock:
                self._fresh_since = None  # a frozen/late camera is a gap: the resume dwell starts again after it
            self.hold(*cond)
        rec = self._latest
        if rec is not None and rec.trusted:
            age = now - rec.sample.t_capture
            if age > self.cfg.max_pose_age_s:
                with self._lock:
                    self._fresh_since = None  # a gap: the resume dwell starts again
                    code = self._holding_code if self._holding_reason is not None else None
                if code is None or code in ("pose_stale", "pipeline_overloaded"):
                    self.hold(*self._stale(f"pose stale: freshest trusted pose is {1000 * age:.0f} ms old", now,
                                           overloaded=code == "pipeline_overloaded"))
        self.robot.refresh()

    def _stale(self, reason: str, now: float, overloaded: bool = False) -> tuple[str, str]:
        """(code, reason) of a stale-pose hold: ``pipeline_overloaded`` when this computer, not
        the camera, makes the poses late (:mod:`.load`), else ``pose_stale`` with ``reason``.
        ``overloaded``: this stale spell was already put down to the computer; it stays so until
        fresh poses end it (the load window's verdict may waver inside one spell, and one spell
        is one alarm, not an overload and a stale pose in turn)."""
        why = self.load.overloaded(now, self.camera.frame_times, 1.0 / float(self.cfg.camera_fps))
        if not why and overloaded:
            why = "this computer is too slow for the pose pipeline (since this hold began)"
        return ("pipeline_overloaded", f"{reason}: {why}") if why else ("pose_stale", reason)

    def pending_latency(self) -> float | None:
        """Session time (s) the newest target was handed to the robot while its latency is not
        measured yet, or None."""
        with self._lock:
            return None if self._pending_latency_stamp is None else self._pending_latency_set_at

    def after_command(self, t_command: float) -> None:
        """Called after a control step that used the current target: record capture->command latency."""
        with self._lock:
            stamp, self._pending_latency_stamp = self._pending_latency_stamp, None
        if stamp is not None:
            self.latencies_s.append(t_command - stamp)
            self.last_command_t = t_command

    # ================================================================== read side
    def pose_summary(self):
        """``snap.pose`` (:class:`~monotracker.engine.snapshot.PoseSummary`) or None."""
        return _summaries.pose_summary(self)

    def summaries(self):
        """``(camera, pose, robot, scene)`` summaries for the snapshot."""
        return _summaries.summaries(self)

    # ================================================================== clocks
    def advance(self, dt: float) -> None:
        """clock="sim": run camera, registration and control in lock-step for ``dt`` s."""
        self.driver.advance(dt)

    def start_threads(self) -> None:
        """clock="real": start the engine thread (and the robot's control thread)."""
        self.driver.start()

    def shutdown(self) -> None:
        """Stop the threads, disarm and close the robot, stop the camera."""
        self.driver.stop()
        rob = self.robot.rig
        if rob is not None:
            try:
                if self.robot.state() in ("tracking", "holding"):
                    rob.stop_tracking()
                rob.disarm()
            finally:
                rob.close()
        self.camera.shutdown()
