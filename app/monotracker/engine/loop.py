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
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from monotracker.engine import components
from monotracker.engine.alarms import POSE_CODES
from monotracker.engine.gate import PoseGate
from monotracker.engine.snapshot import (
    CameraSummary,
    CommandResult,
    PoseSummary,
    RobotSummary,
    SceneGeometry,
    frozen_array,
)
from monotracker.engine.target import needle_target, tip_and_axis_error
from monotracker.errors import MonoTrackerError

log = logging.getLogger(__name__)

#: holds about a pose stream that stopped being fresh; resuming from them needs resume_dwell_s
FRESHNESS_CODES = ("pose_stale", "camera_freeze")


@dataclass
class _PoseRecord:
    sample: components.PoseSample
    trusted: bool
    code: str
    reason: str


class TrackingLoop:
    """Owns camera rig, pose gate, tracker and arm for a :class:`~monotracker.engine.Session`."""

    def __init__(self, session):
        self.s = session
        cfg = session.config
        self.cfg = cfg
        self._lock = threading.RLock()
        self.gate = PoseGate(cfg.min_fiducials, cfg.max_fre_mm, cfg.max_jump_mm, cfg.max_jump_deg,
                             cfg.confirm_frames)
        self.camera_source = cfg.camera
        self.calibration_path: str | None = None
        saved = session.plan_copy()
        if saved.camera_source and saved.camera_source == cfg.camera:
            self.calibration_path = saved.calibration_path  # the calibration used last time
        self.rig: components.CameraRig | None = None
        self.robot: components.RobotRig | None = None
        self.camera_error: str | None = None
        self.fault = "none"
        self._latest: _PoseRecord | None = None
        self._last_trusted: components.PoseSample | None = None
        self._last_frame_t: float | None = None  # capture time of the newest frame seen
        self._last_frame_seen_at: float | None = None  # session time it arrived
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
        self._robot_connected = True
        self._robot_message = "not connected"
        self._tick_hooks: list = []
        # sim clock bookkeeping
        self._t = 0.0
        self._next_frame_t = 0.0
        self._busy_until = -1.0
        self._in_flight: deque[tuple[float, components.PoseSample]] = deque()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._threads_wanted = False

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

    # ================================================================== robot
    def _ensure_robot(self) -> components.RobotRig:
        if self.robot is None:
            self.robot = components.make_robot_rig(self.cfg, self.s)
            if self._threads_wanted and self.cfg.clock == "real":
                self.robot.start_thread()
            plan = self.s.plan_copy()
            if plan.T_base_cam is None and self.robot.default_T_base_cam is not None:
                self.s.set_hand_eye(self.robot.default_T_base_cam)
        return self.robot

    def robot_state(self) -> str:
        with self._lock:
            return self._robot_state

    def _refresh_robot_state(self) -> None:
        if self.robot is None:
            return
        st = self.robot.status()
        with self._lock:
            old, self._robot_state = self._robot_state, st.state
            was_conn, self._robot_connected = self._robot_connected, st.connected
            self._robot_message = st.message
        if not st.connected and was_conn:
            self._alert_once("robot_disconnected", "alarm", "robot_disconnected",
                             "robot connection lost; the arm controller stops the arm, tracking ended",
                             {"state": st.state})
        elif st.connected and not was_conn:
            self._clear_alert("robot_disconnected")
            self.s.alert("info", "robot_connected", "robot connection restored")
        self._sync_robot_alarms(st)
        if st.state != old:
            self.s.record("robot_state", f"robot {old} -> {st.state}" + (f" ({st.message})" if st.message else ""),
                          {"from": old, "to": st.state})

    def _sync_robot_alarms(self, st) -> None:
        """Active conditions that mirror the robot's state: e-stop latched, connection lost."""
        board, now = self.s._alarm_board, self.now()
        if st.state == "estopped":
            board.set("estop", "EMERGENCY STOP latched: arm stopped" + (f" ({st.message})" if st.message else "")
                      + "; reset the e-stop to continue", now)
        else:
            board.clear("estop", now)
        if not st.connected:
            board.set("robot_disconnected", "robot connection lost: the arm controller stopped the arm", now)
        else:
            board.clear("robot_disconnected", now)

    def arm(self) -> CommandResult:
        """Arm the robot (the PIN was checked by the session); needs a fresh trusted pose
        registered for the current plan (see :meth:`invalidate_pose`)."""
        rec, _now, why = self._wait_for_fresh_pose()
        if why is not None:
            return self._refuse("arm", f"no trusted, fresh pose for this plan ({why}); start the camera "
                                       "and wait for a valid pose")
        try:
            rob = self._ensure_robot()
        except MonoTrackerError as exc:
            return CommandResult(False, str(exc))
        r = rob.arm()
        self._refresh_robot_state()
        self.s.record("arm" if r.ok else "arm_refused", "robot armed" if r.ok else f"arming refused: {r.message}",
                      level="info" if r.ok else "warning")
        return r

    def disarm(self) -> CommandResult:
        if self.robot is None:
            return CommandResult(True, "already disarmed")
        r = self.robot.disarm()
        self._refresh_robot_state()
        self.s.record("disarm", "robot disarmed" if r.ok else f"disarm refused: {r.message}")
        return r

    def start_tracking(self) -> CommandResult:
        if self.robot is None or self.robot_state() not in ("armed", "holding", "tracking"):
            return self._refuse("start_tracking", "arm the robot first")
        plan = self.s.plan_copy()
        if not plan.path_complete:
            return self._refuse("start_tracking", "plan the entry and the target first")
        if plan.T_base_cam is None:
            return self._refuse("start_tracking", "no hand-eye calibration (T_base_cam)")
        rec, now, why = self._wait_for_fresh_pose()
        if why is not None:
            return self._refuse("start_tracking", f"no trusted, fresh pose ({why})")
        with self._lock:
            dwelling = self._holding_code in FRESHNESS_CODES
        if dwelling:
            self._resume("operator started tracking on a fresh pose", self._registration_data(rec.sample))
        self._push_target(rec.sample, now)
        r = self.robot.start_tracking()
        self._refresh_robot_state()
        if r.ok:
            self.s.record("tracking_started", "tracking started",
                          {"registration": self._registration_data(rec.sample), "T_base_target_mm":
                           None if self._target_T is None else self._target_T.tolist()})
        else:
            self.s.record("tracking_refused", f"tracking refused: {r.message}", level="warning")
        return r

    def _fresh_pose_now(self):
        """``(record, now, None)`` when the newest pose is trusted and younger than max_pose_age_s;
        else ``(record, now, why)``. Inside the resume dwell after a stale episode a fresh pose is
        enough: the operator's Start confirms it (the dwell only keeps *automatic* resumes from
        flapping; the age limit is the same)."""
        rec, now = self._latest, self.now()
        with self._lock:
            code, reason = self._holding_code, self._holding_reason
            new_since_hold = self._latest_arrival > self._hold_began
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
        return rec, now, None

    def _wait_for_fresh_pose(self):
        """Start tracking on a loaded machine: while trusted poses keep arriving (or the gate is
        confirming a new lock), a click that lands between two of them (or inside a short stale
        episode) waits for the next fresh one,
        up to ``start_wait_s`` (real clock only; the simulated clock cannot advance here)."""
        rec, now, why = self._fresh_pose_now()
        if why is None or self.cfg.clock != "real" or self.cfg.start_wait_s <= 0:
            return rec, now, why
        deadline = time.monotonic() + self.cfg.start_wait_s
        while (why is not None and time.monotonic() < deadline and rec is not None
               and (rec.trusted or rec.code == "acquiring")):  # poses flow (or are being confirmed)
            time.sleep(0.01)
            rec, now, why = self._fresh_pose_now()
        return rec, now, why

    def _refuse(self, code: str, msg: str) -> CommandResult:
        self.s.record(f"{code}_refused", f"{code.replace('_', ' ')} refused: {msg}", level="warning")
        return CommandResult(False, msg)

    def stop_tracking(self) -> CommandResult:
        if self.robot is None:
            return CommandResult(True, "not tracking")
        r = self.robot.stop_tracking()
        self._refresh_robot_state()
        self.s.record("tracking_stopped", "tracking stopped by the operator")
        return r

    def estop(self) -> CommandResult:
        if self.robot is None:
            self.s.alert("alarm", "estop", "EMERGENCY STOP (no robot connected)")
            return CommandResult(True, "e-stop (no robot)")
        r = self.robot.estop()
        self._refresh_robot_state()
        self.s.alert("alarm", "estop", "EMERGENCY STOP pressed; arm stopped and latched")
        return r

    def reset_estop(self) -> CommandResult:
        if self.robot is None:
            return CommandResult(True, "nothing to reset")
        r = self.robot.reset()
        self._refresh_robot_state()
        self.s.record("estop_reset", "e-stop reset; robot disarmed" if r.ok else f"e-stop reset refused: {r.message}")
        return r

    # ================================================================== camera
    def set_camera(self, source: str, calibration_path: str | None) -> CommandResult:
        source = str(source)
        if not (source in ("sim", "sim-points") or source.split(":", 1)[0] in ("device", "file", "folder")):
            return CommandResult(False, "camera must be 'sim', 'sim-points', 'device:N', 'file:PATH' or 'folder:PATH'")
        if self.rig is not None and self.rig.running:
            return CommandResult(False, "stop the camera first")
        if self.robot_state() == "tracking":
            return CommandResult(False, "stop tracking first")
        self.camera_source, self.calibration_path = source, calibration_path
        self.s.record("camera_set", f"camera source {source}" + (f", calibration {calibration_path}" if calibration_path else ""),
                      {"source": source, "calibration_path": calibration_path})
        return CommandResult(True, f"camera {source}")

    def start_camera(self) -> CommandResult:
        plan = self.s.plan_copy()
        if not plan.fiducials_locked:
            return CommandResult(False, "confirm the CT fiducials before starting the camera")
        if self.rig is not None and self.rig.running:
            return CommandResult(True, "camera already running")
        try:
            rig = components.make_camera_rig(self.camera_source, self.calibration_path, plan, self.cfg, self.s)
        except MonoTrackerError as exc:
            self.camera_error = str(exc)
            self.invalidate_pose("camera could not start")
            self.s._alarm_board.set("camera_failed", f"camera could not start: {exc}", self.now())
            self.s.alert("alarm", "camera_failed", f"camera could not start: {exc}")
            return CommandResult(False, str(exc))
        self.s._alarm_board.clear_all(("camera_failed", "camera_stopped", "camera_uncalibrated"), self.now())
        with self._lock:
            self.rig = rig
            self.camera_error = None
            self._last_frame_seen_at = self.now()
            self._next_frame_t = self.now()
            self.gate.reset()
            anchor = plan.entry_lps_mm if plan.entry_lps_mm is not None else plan.fiducial_centres().mean(axis=0)
            self.gate.set_anchor(anchor)
        self.s._store_camera(self.camera_source, self.calibration_path, rig.K, rig.dist, rig.image_size)
        if rig.default_T_base_cam is not None and plan.T_base_cam is None:
            self.s.set_hand_eye(rig.default_T_base_cam)
        if self.cfg.clock == "real":
            rig.start()
        rig.running = True
        self.s.record("camera_started", f"camera {self.camera_source} started",
                      {"source": self.camera_source, "K": None if rig.K is None else np.asarray(rig.K).tolist()})
        return CommandResult(True, "camera started")

    def stop_camera(self) -> CommandResult:
        rig = self.rig
        if rig is None or not rig.running:
            return CommandResult(True, "camera not running")
        rig.running = False
        rig.stop()
        self.s.record("camera_stopped", "camera stopped")
        self.s._alarm_board.clear_all(POSE_CODES + ("camera_uncalibrated",), self.now())
        self._hold("camera_stopped", "camera stopped")
        self.invalidate_pose("camera stopped", hold=False)
        return CommandResult(True, "camera stopped")

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
            self.gate.reset()
        if hold and self.robot_state() in ("tracking", "holding"):
            self._hold("pose_lost", f"pose cleared: {why}")
        if had:
            self.s.record("pose_invalidated", f"pose cleared: {why}", {"why": why})

    def plan_changed(self, why: str, restart_camera: bool) -> None:
        """The plan's fiducials, path or CT changed: the pose (and a running camera rig, built with
        the old fiducials and target) belong to the old plan. Stop the camera, forget the pose and,
        if ``restart_camera`` and the camera was running, start it again on the new plan."""
        rig = self.rig
        was_running = rig is not None and rig.running
        if was_running:
            rig.running = False
            rig.stop()
            self.s.record("camera_stopped", f"camera stopped: {why}")
        self.invalidate_pose(why)
        if was_running and restart_camera:
            r = self.start_camera()
            if not r.ok:
                self.s.alert("warning", "camera_stopped", f"camera stopped ({why}) and could not restart: {r.message}")
        elif was_running:
            self._hold("camera_stopped", f"camera stopped: {why}")

    def latest_frame(self):
        rig = self.rig
        return None if rig is None else rig.latest_frame()

    # ================================================================== faults (sim only)
    def inject_fault(self, name: str) -> CommandResult:
        if name == "none":
            self.fault = "none"
            if self.rig is not None:
                self.rig.set_fault("none")
            self.s.record("fault_cleared", "fault injection cleared")
            return CommandResult(True, "fault cleared")
        if not self.camera_source.startswith("sim") or self.cfg.robot != "sim":
            return CommandResult(False, "fault injection is for the simulated camera and arm only")
        if name == "robot-disconnect":
            if self.robot is None:
                return CommandResult(False, "no robot to disconnect")
            self.robot.inject_disconnect()
        else:
            if self.rig is None:
                return CommandResult(False, "start the camera first")
            self.rig.set_fault(name)
        self.fault = name
        self.s.record("fault_injected", f"fault injected: {name}", {"fault": name}, level="warning")
        return CommandResult(True, f"fault {name} injected")

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
        v = self.gate.check(sample.ok, sample.reason, sample.T_cam_ct, sample.n_matched, sample.fre_mm,
                            sample.t_capture)
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
            code = {"occlusion": "occlusion", "fre": "bad_pose", "jump": "pose_jump", "estimator": "pose_lost",
                    "acquiring": "acquiring"}[v.code]
            level = "info" if code == "acquiring" else "warning"
            self._hold(code, v.reason, level)

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
        T = needle_target(plan.T_base_cam, sample.T_cam_ct, plan.entry_lps_mm, plan.target_lps_mm, ref_R)
        with self._lock:
            self._target_T, self._target_stamp = T, sample.t_capture
            self._pending_latency_stamp = sample.t_capture
            self._pending_latency_set_at = now
        self.robot.set_target(T, sample.t_capture, True, plan.T_base_cam @ sample.T_cam_ct)

    def _hold(self, code: str, reason: str, level: str = "warning") -> None:
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
        lvl = "alarm" if code in ("camera_freeze", "robot_disconnected", "engine_error") else level
        self.s.alert(lvl, code, msg, {"reason": reason, "tracking": tracking, "unreported_episodes": unreported})

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
        rig = self.rig
        if rig is not None and rig.running:
            seen = self._last_frame_seen_at
            if seen is not None and now - seen > self.cfg.freeze_after_s:
                self._hold("camera_freeze", f"camera frozen: no new frame for {1000 * (now - seen):.0f} ms")
        rec = self._latest
        if rec is not None and rec.trusted:
            age = now - rec.sample.t_capture
            if age > self.cfg.max_pose_age_s:
                with self._lock:
                    self._fresh_since = None  # a gap: the resume dwell starts again
                if self._holding_reason is None:
                    self._hold("pose_stale", f"pose stale: freshest trusted pose is {1000 * age:.0f} ms old")
        self._refresh_robot_state()

    def note_frame(self, t_capture: float, now: float) -> bool:
        """A frame with capture time ``t_capture`` arrived; True if it is new. Only new frames
        refresh the freeze watchdog (a frozen camera repeats its last frame)."""
        with self._lock:
            if self._last_frame_t is not None and t_capture <= self._last_frame_t:
                return False
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

    # ================================================================== sim clock
    def advance(self, dt: float) -> None:
        if dt < 0:
            raise MonoTrackerError("advance needs dt >= 0")
        period = 1.0 / self.cfg.control_hz
        frame_period = 1.0 / self.cfg.camera_fps
        n = int(round(dt / period))
        for _ in range(n):
            self._t += period
            t = self._t
            self.s.clock.set(t)
            rig = self.rig
            if rig is not None and rig.running and t + 1e-9 >= self._next_frame_t:
                self._next_frame_t += frame_period
                # frames travel in a pipeline; the estimator takes a frame when it arrives, if free
                if t + rig.transport_delay_s >= self._busy_until - 1e-12:
                    frame = rig.capture(t)
                    # A frozen camera hands back the same frame: nothing new to estimate.
                    if frame is not None and self.note_frame(frame.t_capture, t):
                        # compute time of detection + registration: this thread's CPU time, so
                        # the model does not depend on what else the machine runs meanwhile
                        w0 = time.thread_time()
                        sample = rig.estimate(frame)
                        w = time.thread_time() - w0
                        ready = t + rig.transport_delay_s + w
                        sample.t_ready = ready
                        self._busy_until = ready
                        self._in_flight.append((ready, sample))
            while self._in_flight and self._in_flight[0][0] <= t + 1e-12:
                _, sample = self._in_flight.popleft()
                self.on_pose(sample, t)
            self.watchdogs(t)
            if self.robot is not None:
                self.robot.step(t)
                self.after_command(t)
                self._refresh_robot_state()
            for fn in self._tick_hooks:
                fn(self, t)

    # ================================================================== real clock
    def start_threads(self) -> None:
        self._threads_wanted = True
        if self.cfg.clock != "real" or self._thread is not None:
            return
        if self.robot is not None:
            self.robot.start_thread()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="monotracker-loop", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period = 1.0 / 250.0
        last_seen = None
        while not self._stop.is_set():
            now = self.now()
            try:
                rig = self.rig
                if rig is not None and rig.running:
                    for frame_t in rig.poll_frames():
                        self.note_frame(frame_t, now)
                    sample = rig.latest_sample()
                    if sample is not None and sample is not last_seen:
                        last_seen = sample
                        self.on_pose(sample, now)
                self.watchdogs(now)
                if self.robot is not None and self._pending_latency_stamp is not None:
                    st = self.robot.status()
                    # the first control step after the target was handed over used it
                    if st.t_command is not None and st.t_command >= self._pending_latency_set_at:
                        self.after_command(st.t_command)
                self.s._alarm_board.clear("engine_error", now)
            except Exception:  # noqa: BLE001 - the loop must survive; hold the arm and report
                log.exception("engine loop iteration failed")
                self._on_iteration_error()
            self._stop.wait(period)

    def _on_iteration_error(self) -> None:
        """After a failed loop iteration: hold the arm and raise the alarm. If holding itself fails
        (e.g. the robot call that failed is the one the hold needs), stop tracking outright so an
        exception can never leave the arm following the last target; the loop thread survives."""
        try:
            self._hold("engine_error", "internal engine error; arm holding (see log)")
        except Exception:  # noqa: BLE001 - last resort, must not kill the engine thread
            log.exception("holding after an engine error failed; stopping tracking")
            try:
                if self.robot is not None:
                    self.robot.stop_tracking()
            except Exception:  # noqa: BLE001
                log.exception("stop_tracking after an engine error failed")

    def shutdown(self) -> None:
        self._stop.set()
        th = self._thread
        if th is not None:
            th.join(2.0)
            self._thread = None
        if self.robot is not None:
            try:
                if self.robot_state() in ("tracking", "holding"):
                    self.robot.stop_tracking()
                self.robot.disarm()
            finally:
                self.robot.close()
        if self.rig is not None:
            self.rig.running = False
            self.rig.stop()

    # ================================================================== snapshots
    def pose_summary(self) -> PoseSummary | None:
        rec = self._latest
        if rec is None:
            return None
        smp = rec.sample
        now = self.now()
        with self._lock:
            code, why = self._holding_code, self._holding_reason
        stale = rec.trusted and code in FRESHNESS_CODES  # the engine holds for staleness: say so
        return PoseSummary(
            t=smp.t_capture, age_s=now - smp.t_capture, ok=smp.ok, trusted=rec.trusted and not stale,
            reason=(why or "pose is stale") if stale else (rec.reason if not rec.trusted else
                                                           (smp.reason or "pose trusted")),
            T_cam_ct=frozen_array(smp.T_cam_ct), n_visible=smp.n_matched,
            fiducial_status=dict(smp.fiducial_status), residuals_px=dict(smp.residuals_px),
            fre_mm=smp.fre_mm, predicted_tre_mm=smp.predicted_tre_mm,
            latency_ms=None if smp.t_ready is None else 1000 * (smp.t_ready - smp.t_capture),
            truth_tre_mm=smp.truth_tre_mm, stale=stale,
        )

    def summaries(self):
        rig = self.rig
        times = list(self._frame_times)
        fps = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 2 and times[-1] > times[0] else 0.0
        cam = CameraSummary(
            source=self.camera_source, running=bool(rig is not None and rig.running), fps=float(fps),
            K=frozen_array(None if rig is None else rig.K), dist=frozen_array(None if rig is None else rig.dist),
            image_size=None if rig is None else rig.image_size, calibration_path=self.calibration_path,
            error=self.camera_error, frames=self._frames,
        )
        pose = self.pose_summary()
        plan = self.s.plan_copy()
        T_cam_ct = None if self._last_trusted is None else self._last_trusted.T_cam_ct
        T_base_ct = None if (T_cam_ct is None or plan.T_base_cam is None) else plan.T_base_cam @ T_cam_ct
        q = T_tip = None
        tip_err = ang_err = None
        speed = 0.0
        lat = 1000 * self.latencies_s[-1] if self.latencies_s else None
        if self.robot is not None:
            st = self.robot.status()
            q, T_tip, speed = st.q, st.T_base_tip, st.speed_mm_s
            if T_tip is not None and T_base_ct is not None and plan.path_complete:
                tip_err, ang_err = tip_and_axis_error(T_tip, T_base_ct, plan.entry_lps_mm, plan.target_lps_mm)
            robot = RobotSummary(st.state, frozen_array(q), tip_err, ang_err, float(speed), st.connected,
                                 self._holding_reason or st.message, lat)
        else:
            robot = RobotSummary("disarmed", None, None, None, 0.0, False, "robot not connected yet", None)
        scene = SceneGeometry(frozen_array(plan.T_base_cam), frozen_array(T_cam_ct), frozen_array(T_base_ct),
                              frozen_array(T_tip), frozen_array(self._target_T), frozen_array(q))
        return cam, pose, robot, scene
