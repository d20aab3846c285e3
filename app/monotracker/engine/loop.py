"""The loop wiring: camera -> pose -> trust gate -> needle target -> tracker -> arm.

Rates and threads (clock="real", the web app):

* camera + registration: the vision pose stream's own thread (``PoseStream``), at camera rate or
  as fast as registration allows (it always works on the newest frame, dropping older ones);
* control: the robot ``Tracker``'s real-time thread at ``control_hz``;
* the engine thread (``monotracker-loop``, 250 Hz) moves the freshest pose into the tracker and
  runs the watchdogs: camera freeze (no new frame for ``freeze_after_s``), stale pose (freshest
  trusted pose older than ``max_pose_age_s``), robot connection and state changes.

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
from collections import deque
from dataclasses import dataclass

import numpy as np

from monotracker.engine import components
from monotracker.engine.alarms import FRESHNESS_CODES, POSE_CODES, VERDICT_CODES, level_of
from monotracker.engine.gate import PoseGate
from monotracker.engine.loop_camera import CameraCommands
from monotracker.engine.loop_clocks import LoopClocks
from monotracker.engine.loop_robot import RobotCommands
from monotracker.engine.loop_summaries import LoopSummaries

log = logging.getLogger(__name__)



@dataclass
class _PoseRecord:
    sample: components.PoseSample
    trusted: bool
    code: str
    reason: str


class TrackingLoop(RobotCommands, CameraCommands, LoopSummaries, LoopClocks):
    """Owns camera rig, pose gate, tracker and arm for a :class:`~monotracker.engine.Session`."""

    def __init__(self, session):
        self.s = session
        cfg = session.config
        self.cfg = cfg
        self._lock = threading.RLock()
        self.gate = PoseGate(cfg.min_fiducials, cfg.max_fre_mm, cfg.max_jump_mm, cfg.max_jump_deg,
                             cfg.confirm_frames, max_predicted_tre_mm=cfg.max_predicted_tre_mm)
        self.camera_source = cfg.camera
        self.calibration_path: str | None = None
        saved = session.plan_copy()
        if saved.camera_source and saved.camera_source == cfg.camera:
            self.calibration_path = saved.calibration_path  # the calibration used last time
        self.rig: components.CameraRig | None = None
        self._rig_fiducials: np.ndarray | None = None
        self.robot: components.RobotRig | None = None
        self.camera_error: str | None = None
        self.fault = "none"
        self._latest: _PoseRecord | None = None
        self._last_trusted: components.PoseSample | None = None
        self._last_frame_t: float | None = None  # capture time of the newest frame seen
        self._last_frame_seen_at: float | None = None  # session time it arrived
        self._last_digest = None  # content checksum of the newest frame (None: the rig gives none)
        self._repeat_frames = 0  # bit-identical repeats since the last new frame (a frozen camera)
        self._frames = 0
        self._frame_times: deque[float] = deque(maxlen=90)
        self._holding_reason: str | None = None  # why the loop currently holds (None = not holding)
        self._holding_code: str | None = None
        self._hold_reported = False  # the current hold episode was reported (so its end is too)
        self._fresh_since: float | None = None  # trusted poses arriving fresh without a gap since (s)
        self._dwell_s = cfg.resume_dwell_s  # current resume dwell (doubles while the stream keeps failing)
        self._fresh_resumed_at = -np.inf  # when tracking last resumed after a freshness hold
        self._hold_began = -np.inf  # when the current hold's cause was set
        self._latest_arrival = -np.inf  # when the newest estimate reached the loop
        self._seen_ids: set | None = None  # fiducial ids seen in the previous estimate
        self._alerted: set[str] = set()
        self._target_T: np.ndarray | None = None
        self._target_stamp: float | None = None
        self._pending_latency_stamp: float | None = None
        self._pending_latency_set_at = 0.0
        self.latencies_s: deque[float] = deque(maxlen=5000)
        self._robot_state = "disarmed"
        self._audited_state = "disarmed"  # the state the newest robot_state audit row went to
        self._robot_audit_lock = threading.Lock()  # robot_state rows are written in order, one writer at a time
        self._robot_connected = True
        self._robot_message = "not connected"
        self._tick_hooks: list = []
        self._pose_hooks: list = []
        # sim clock bookkeeping
        self._t = 0.0
        self._next_frame_t = 0.0
        self._busy_until = -1.0
        self._in_flight: deque[tuple[float, components.PoseSample]] = deque()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._threads_wanted = False
        self.priority = ""  # what the OS granted the engine thread (pipeline_priority)
        self.process_priority = ""  # ... and the engine process's threads

    # ================================================================== plumbing
    def now(self) -> float:
        return float(self.s.clock())

    def _mark(self, key: str) -> bool:
        """True the first time ``key`` is raised in this episode (thread-safe)."""
        with self._lock:
            if key in self._alerted:
                return False
            self._alerted.add(key)
            return True

    def _alert_once(self, key: str, level: str, code: str, message: str, data: dict | None = None) -> None:
        if self._mark(key):
            self.s.alert(level, code, message, data)

    def _clear_alert(self, key: str) -> bool:
        with self._lock:
            if key in self._alerted:
                self._alerted.discard(key)
                return True
            return False

    def add_tick_hook(self, fn) -> None:
        """``fn(loop, t)`` after every control tick (clock="sim"): metrics for demo/benchmark."""
        self._tick_hooks.append(fn)

    def add_pose_hook(self, fn) -> "callable":
        """``fn(loop, sample, trusted, now)`` after every estimate the loop handles (both clocks, on
        the engine thread: keep it short, hand heavy work to your own thread). A hook that raises
        is logged and never disturbs the loop. Returns the function that removes the hook."""
        with self._lock:
            self._pose_hooks = self._pose_hooks + [fn]

        def remove() -> None:
            with self._lock:
                self._pose_hooks = [h for h in self._pose_hooks if h is not fn]
        return remove

    def _run_pose_hooks(self, sample, trusted: bool, now: float) -> None:
        for fn in self._pose_hooks:
            try:
                fn(self, sample, trusted, now)
            except Exception:  # recording/streaming must never hold the arm
                log.exception("pose hook failed")

    def target(self) -> tuple:
        """(T_base_target 4x4 mm or None, its capture stamp or None): the needle target last handed
        to the tracker."""
        with self._lock:
            return self._target_T, self._target_stamp

    # ================================================================== the loop proper
    def _fiducial_changes(self, sample: components.PoseSample) -> None:
        """Info alerts when fiducials vanish from / come back into the camera's view."""
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
            self.s.alert("info", "fiducials_lost", f"fiducial{'s' if len(lost) > 1 else ''} "
                         f"{', '.join(map(str, lost))} out of view ({n} of {total} seen; {verdict})",
                         {"lost": lost, "seen": sorted(seen)})
        if back:
            self.s.alert("info", "fiducials_back", f"fiducial{'s' if len(back) > 1 else ''} "
                         f"{', '.join(map(str, back))} back in view ({n} of {total} seen)",
                         {"back": back, "seen": sorted(seen)})

    def on_pose(self, sample: components.PoseSample, now: float) -> None:
        """A new estimate is available (engine thread / sim tick)."""
        self._fiducial_changes(sample)
        for fid, shift in getattr(sample, "moved", {}).items():
            self.s._persistent_alarm("fiducial_moved", f"fiducial {fid} moved about {shift:.1f} mm relative to the "
                         "others since the CT: excluded from registration (check it is firmly attached)",
                         {"fiducial": fid, "shift_mm": shift})
        v = self.gate.check(sample.ok, sample.reason, sample.T_cam_ct, sample.n_matched, sample.fre_mm,
                            sample.t_capture, code=getattr(sample, "code", ""),
                            predicted_tre_mm=sample.predicted_tre_mm)
        rec = _PoseRecord(sample, v.trusted, v.code, v.reason)
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
            self._hold("pose_stale", f"pose stale: trusted pose arrived {1000 * age:.0f} ms after capture "
                                     f"(limit {1000 * limit:.0f} ms)")
        elif v.trusted:
            dwell = self._dwell_s
            if holding and code == "camera_freeze" and self._camera_frozen(now):
                # a pose captured before the freeze, still in flight when it was detected: the
                # camera is still frozen, so it must not resume tracking (not even for a cycle),
                # and it does not count towards the fresh run the resume dwell asks for
                with self._lock:
                    self._fresh_since = None
                self._run_pose_hooks(sample, v.trusted, now)
                return
            if holding and code in FRESHNESS_CODES and fresh_for < dwell:
                # hysteresis: after a stale/frozen stream, resume only once poses have been
                # arriving fresh for resume_dwell_s (the arm keeps holding meanwhile)
                with self._lock:
                    self._holding_reason = (f"pose stale: fresh again for {1000 * fresh_for:.0f} ms; resuming after "
                                            f"{1000 * dwell:.0f} ms")
                return
            self._push_target(sample, now)
            if holding:
                self._resume(f"pose trusted again ({sample.n_matched} fiducials)", self._registration_data(sample))
        else:
            self._hold(VERDICT_CODES.get(v.code, v.code), v.reason)
        self._run_pose_hooks(sample, v.trusted, now)

    def _push_target(self, sample: components.PoseSample, now: float) -> None:
        plan = self.s.plan_copy()
        if not plan.path_complete or plan.T_base_cam is None or self.robot is None:
            return
        ref_R = None
        st = self.robot.status()
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
        self.robot.set_target(T, sample.t_capture, True, plan.T_base_cam @ sample.T_cam_ct)

    def _hold(self, code: str, reason: str) -> None:
        """Make the tracker hold still (valid=False) and raise the alert once per episode.

        ``acquiring`` (waiting for the first consistent poses) is recorded as an event, not an alert."""
        if self.robot is not None:
            self.robot.set_target(self._target_T, self._target_stamp if self._target_stamp is not None else self.now(),
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
        tracking = self.robot_state() in ("tracking", "holding")
        msg = reason + ("; arm holding still" if tracking else "")
        report = self._set_pose_alarm(code, msg, tracking)
        if not self._mark(code):
            return
        self._hold_reported = self._hold_reported or report
        if not report:
            return  # a technical condition again within its quiet time: shown, counted, not re-reported
        unreported = self.s._alarm_board.unreported(code)
        if unreported:
            msg += f" ({unreported} more short episode{'s' if unreported > 1 else ''} since the last report)"
        if code == "acquiring":
            self.s.record("pose_acquiring", reason)
            return
        self.s.alert(level_of(code, "warning"), code, msg, {"reason": reason, "tracking": tracking,
                                                             "unreported_episodes": unreported})

    def _set_pose_alarm(self, code: str, message: str, tracking: bool) -> bool:
        """Show why the arm holds (one pose condition at a time); True when it is to be reported.
        A stopped camera is a condition only while the arm is armed; the rest always are (the
        registration view needs them too), as alarms while the arm follows the head."""
        board, now = self.s._alarm_board, self.now()
        if code == "camera_stopped" and self.robot_state() in ("disarmed", "estopped"):
            board.clear_all(POSE_CODES, now)
            return True
        if code != "engine_error":
            board.clear_all(POSE_CODES, now, keep=code)
        return board.set(code, message, now, level="alarm" if tracking else None)

    @staticmethod
    def _registration_data(smp: components.PoseSample) -> dict:
        """What the audit log keeps about a registration (JSON-ready)."""
        return {"t_capture": smp.t_capture, "frame": smp.frame_index, "n_matched": smp.n_matched,
                "fre_mm": smp.fre_mm, "predicted_tre_mm": smp.predicted_tre_mm,
                "T_cam_ct_mm": None if smp.T_cam_ct is None else np.asarray(smp.T_cam_ct).tolist()}

    def _resume(self, why: str, data: dict | None = None) -> None:
        with self._lock:
            was, code = self._holding_reason, self._holding_code
            self._holding_reason = self._holding_code = None
            if code in FRESHNESS_CODES:
                self._fresh_resumed_at = self.now()
            self._alerted &= {"robot_disconnected"}
            reported, self._hold_reported = self._hold_reported, False
        self.s._alarm_board.clear_all(tuple(c for c in POSE_CODES if c != "engine_error"), self.now())
        if was is None or not reported:
            return  # an unreported (rate-limited) hold ends unreported too
        if code == "acquiring":
            self.s.record("registration", f"registration acquired: {why}", data)
            return
        tracking = self.robot_state() in ("tracking", "holding")
        self.s.alert("info", "resumed", why + ("; tracking resumed" if tracking else ""),
                     {"after": was, "cause": code, "registration": data})

    def watchdogs(self, now: float) -> None:
        """Camera freeze, stale pose, robot state (every engine tick)."""
        frozen = self._camera_frozen(now)
        if frozen:
            with self._lock:
                self._fresh_since = None  # a frozen camera is a gap: the resume dwell starts again after it
            self._hold("camera_freeze", frozen)
        rec = self._latest
        if rec is not None and rec.trusted:
            age = now - rec.sample.t_capture
            if age > self.cfg.max_pose_age_s:
                with self._lock:
                    self._fresh_since = None  # a gap: the resume dwell starts again
                if self._holding_reason is None:
                    self._hold("pose_stale", f"pose stale: freshest trusted pose is {1000 * age:.0f} ms old")
        self._refresh_robot_state()

    def _camera_frozen(self, now: float) -> str | None:
        """Why the camera counts as frozen now (the hold's reason), or None: its last frame(s)
        repeated bit for bit, or no new frame for ``freeze_after_s``. A rig that watches its own
        camera (StreamRig) reports freezes as estimates with a code instead: None here."""
        rig = self.rig
        if rig is None or not rig.running or getattr(rig, "watches_itself", False):
            return None
        seen = self._last_frame_seen_at
        if self._repeat_frames:
            return (f"camera frozen: {self._repeat_frames} frame(s) repeated bit for bit "
                    f"(last new frame {1000 * (now - seen):.0f} ms ago)")
        if seen is not None and now - seen > self.cfg.freeze_after_s:
            return f"camera frozen: no new frame for {1000 * (now - seen):.0f} ms"
        return None

    def note_frame(self, t_capture: float, now: float, digest=None) -> bool:
        """A frame with capture time ``t_capture`` arrived; True if it is new. Only new frames
        refresh the freeze watchdog (a frozen camera repeats its last frame). ``digest``: a
        checksum of the content; equal to the previous frame's, the frame is a bit-identical
        repeat (a frozen camera; sensor noise never repeats a frame) and the freeze alarm holds
        the arm at the next watchdog tick, without waiting ``freeze_after_s``."""
        with self._lock:
            if self._last_frame_t is not None and t_capture <= self._last_frame_t:
                return False
            if digest is not None and digest == self._last_digest:
                self._last_frame_t = t_capture
                self._repeat_frames += 1
                return False
            self._last_digest = digest
            self._repeat_frames = 0
            self._last_frame_t = t_capture
            self._last_frame_seen_at = now
            self.s._alarm_board.clear("camera_freeze", now)
            self._frames += 1
            self._frame_times.append(now)
            return True

    def after_command(self, t_command: float) -> None:
        """Called after a control step that used the current target: record capture->command latency."""
        with self._lock:
            stamp, self._pending_latency_stamp = self._pending_latency_stamp, None
        if stamp is not None:
            self.latencies_s.append(t_command - stamp)
