"""The tracking loop's robot commands: arm, disarm, start/stop tracking, e-stop, reset.

Each refuses with a one-line reason; arming and tracking need the plan checks and a fresh
trusted pose for this plan. Mixed into :class:`~monotracker.engine.loop.TrackingLoop`, whose
state (``self.s`` the session, ``self.robot``, the pose records) these methods use."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from monotracker.engine import components
from monotracker.engine.alarms import FRESHNESS_CODES
from monotracker.engine.snapshot import CommandResult
from monotracker.errors import MonoTrackerError
from monotracker.robot.safety import SafetyConfig

log = logging.getLogger(__name__)

#: The robot's safety layer starts tracking only while its newest target *arrived* within its
#: frame-gap limit (``SafetyConfig.stale_s``, 0.1 s), a rule apart from the engine's age limit
#: (``max_pose_age_s``, capture -> now): a pose captured 140 ms ago is fresh for the engine but,
#: arrived 100 ms ago, stale for the arm, which refused the start ("no fresh valid target pose")
#: next to "Pose: VALID" on a loaded machine. On a real clock Start is therefore sent only while
#: the newest pose arrived within half that gap (the other half for the start command's way to
#: the control process), waiting for the next pose up to ``start_wait_s``.
START_ARRIVAL_S = SafetyConfig().stale_s / 2


class RobotCommands:
    """The tracking loop's robot commands: arm, disarm, start/stop tracking, e-stop, reset (part of :class:`~monotracker.engine.loop.TrackingLoop`)."""

    #: serialises robot creation (``connect_robot`` from the browser's Calibrate step and
    #: ``arm`` may race: two callers must never build two arm connections); class-wide because
    #: the mixin has no ``__init__`` of its own, and creation is rare
    _robot_create_lock = threading.Lock()

    def _ensure_robot(self) -> components.RobotRig:
        """The robot rig, created (and connected) on first use; thread-safe: concurrent
        callers get the same rig. Raises ``MonoTrackerError`` when it cannot be created."""
        rob = self.robot
        if rob is not None:
            return rob
        with self._robot_create_lock:
            if self.robot is None:  # checked again: another caller may have created it meanwhile
                rob = components.make_robot_rig(self.cfg, self.s)
                with self._lock:
                    self.robot = rob
                if self._threads_wanted and self.cfg.clock == "real":
                    rob.start_thread()
                plan = self.s.plan_copy()
                if plan.T_base_cam is None and rob.default_T_base_cam is not None:
                    self.s.set_hand_eye(rob.default_T_base_cam)
        return self.robot

    def robot_state(self) -> str:
        with self._lock:
            return self._robot_state

    def _refresh_robot_state(self) -> None:
        if self.robot is None:
            return
        st = self.robot.status()
        with self._lock:
            self._robot_state = st.state
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
        self._audit_robot_states(st)

    def _audit_robot_states(self, st) -> None:
        """One ``robot_state`` audit row per state change, in the order the controller made them,
        each with the reason of its own transition (``engine/robot_transitions.py``); the rows
        follow each other (``from`` = the previous row's ``to``; ``monotracker audit verify``
        checks it). A rig that reports no transitions (a test double): the changes seen here."""
        with self._robot_audit_lock:
            rows = self.robot.drain_transitions()
            if rows is None:
                if st.state == self._audited_state:
                    return
                from monotracker.engine.robot_transitions import RobotTransition

                rows = [RobotTransition(self._audited_state, st.state, st.message)]
            for tr in rows:
                if tr.from_state != self._audited_state:
                    # never expected (every transition is reported): say so rather than break the chain
                    self.s.record("robot_state", f"robot {self._audited_state} -> {tr.from_state} (a change the "
                                  "controller did not report)", {"from": self._audited_state, "to": tr.from_state,
                                                                 "reason": "unreported", "t_control": None, "seq": None},
                                  level="warning")
                self.s.record("robot_state", f"robot {tr.from_state} -> {tr.to_state}" + (f" ({tr.reason})" if tr.reason else ""),
                              {"from": tr.from_state, "to": tr.to_state, "reason": tr.reason, "t_control": tr.t,
                               "seq": tr.seq})
                self._audited_state = tr.to_state

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

    def _plan_mismatch(self) -> str | None:
        """The plan's readiness, and whether the running camera registers against this plan's
        fiducial set (a pose computed on another set must not move the arm)."""
        why = self.s.plan_not_ready()
        if why:
            return why
        rig, used = self.rig, self._rig_fiducials
        if rig is not None and rig.running and used is not None:
            now = self.s.plan_copy().fiducial_centres()
            if now.shape != used.shape or not np.array_equal(now, used):
                return "the fiducial set changed since the camera started; stop and start the camera"
        return None

    def arm(self) -> CommandResult:
        """Arm the robot (the PIN was checked by the session); needs a fresh trusted pose
        registered for the current plan (see :meth:`invalidate_pose`)."""
        why = self._plan_mismatch()
        if why:
            return self._refuse("arm", f"the plan is not ready: {why}")
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
        why = self._plan_mismatch()
        if why:
            return self._refuse("start_tracking", f"the plan is not ready: {why}")
        plan = self.s.plan_copy()
        if plan.T_base_cam is None:
            return self._refuse("start_tracking", "no hand-eye calibration (T_base_cam)")
        rec, now, why = self._wait_for_fresh_pose(START_ARRIVAL_S if self.cfg.clock == "real" else None)
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

    def _fresh_pose_now(self, arrival_within_s: float | None = None):
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

    def _wait_for_fresh_pose(self, arrival_within_s: float | None = None):
        """Start tracking on a loaded machine: while trusted poses keep arriving (or the gate is
        confirming a new lock), a click that lands between two of them (or inside a short stale
        episode) waits for the next fresh one (arrived within ``arrival_within_s``, s, when
        given), up to ``start_wait_s`` (real clock only; the simulated clock cannot advance here)."""
        rec, now, why = self._fresh_pose_now(arrival_within_s)
        if why is None or self.cfg.clock != "real" or self.cfg.start_wait_s <= 0:
            return rec, now, why
        deadline = time.monotonic() + self.cfg.start_wait_s
        while (why is not None and time.monotonic() < deadline and rec is not None
               and (rec.trusted or rec.code == "acquiring")):  # poses flow (or are being confirmed)
            time.sleep(0.005 if arrival_within_s is not None else 0.01)
            rec, now, why = self._fresh_pose_now(arrival_within_s)
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

    def signal_estop(self) -> None:
        """The stop channel (``engine/pipeline_priority.py``): straight to the robot's controller,
        before anything else, without the loop's lock; never raises (a failure is logged; the
        full :meth:`estop` that follows reports it)."""
        rob = self.robot
        if rob is None:
            return
        try:
            rob.signal_estop()
        except Exception:  # noqa: BLE001 - the STOP handler must survive; estop() says what failed
            log.exception("signalling the e-stop failed")

    def estop(self) -> CommandResult:
        """Signal the stop, wait (bounded) for the controller's acknowledgement, then record it.
        Without an acknowledgement the ``estop_unconfirmed`` alarm stands until a later stop is
        confirmed."""
        if self.robot is None:
            self.s.alert("alarm", "estop", "EMERGENCY STOP (no robot connected)")
            return CommandResult(True, "e-stop (no robot)")
        r = self.robot.estop()  # signals first, then waits for the acknowledgement
        self._refresh_robot_state()
        board, now = self.s._alarm_board, self.now()
        if r.ok:
            board.clear("estop_unconfirmed", now)
            self.s.alert("alarm", "estop", f"EMERGENCY STOP pressed; arm stopped and latched: {r.message}")
        else:
            board.set("estop_unconfirmed", r.message, now, level="alarm")
            self.s.alert("alarm", "estop_unconfirmed", r.message)
        return r

    def reset_estop(self) -> CommandResult:
        if self.robot is None:
            return CommandResult(True, "nothing to reset")
        r = self.robot.reset()
        self._refresh_robot_state()
        self.s.record("estop_reset", "e-stop reset; robot disarmed" if r.ok else f"e-stop reset refused: {r.message}")
        return r

