"""The tracking loop's robot part: the robot rig and its state, arm (PIN, accuracy verification),
disarm, start/stop tracking, e-stop, reset.

Each command refuses with a one-line reason; arming and tracking need the plan checks and a
fresh trusted pose for this plan. Arming is consent to one plan: a plan revision that reaches an
armed, tracking or holding robot disarms it first (:meth:`RobotControl.disarm_for_revision`,
``plan_changed_armed``). An e-stop pressed before any robot is connected is latched here: arming
is refused until it is reset, and a robot connected meanwhile starts e-stopped. A part of
:class:`~monotracker.engine.loop.core.TrackingLoop` (``loop.robot``); the pose side (holds, the
needle target) is the core's."""

from __future__ import annotations

import logging
import threading

import numpy as np

from monotracker.engine import rigs
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
#: the robot states in which the arm may move
ENGAGED = ("armed", "tracking", "holding")
ESTOP_LATCHED = "the e-stop is latched; reset the e-stop first"


class RobotControl:
    """The robot rig of one tracking loop (see the module docstring). ``loop``: the core (the pose,
    holds, the target); ``plan``: the plan editor; ``access``: the PIN guard (arming); ``session``:
    what the rig factory hands the rigs and the accuracy verification reads."""

    def __init__(self, loop, *, plan, access, session):
        self.loop = loop
        self.cfg = loop.cfg
        self.plan = plan
        self._access = access
        self._session = session
        self._lock = threading.RLock()
        #: serialises robot creation (``connect_robot`` from the browser's Calibrate step and
        #: ``arm`` may race: two callers must never build two arm connections)
        self._create_lock = threading.Lock()
        self.rig: rigs.RobotRig | None = None
        self._state = "disarmed"
        self._connected = True
        self._message = "not connected"
        self._audited_state = "disarmed"  # the state the newest robot_state audit row went to
        self._audit_lock = threading.Lock()  # robot_state rows are written in order, one writer at a time
        self.threads_wanted = False  # the real clock runs: a new rig starts its control thread
        #: an e-stop pressed while no robot was connected: latched until reset_estop (a plain
        #: attribute: the stop channel sets it without a lock)
        self.estop_without_robot = False

    def now(self) -> float:
        return self.loop.now()

    def ensure(self) -> rigs.RobotRig:
        """The robot rig, created (and connected) on first use; thread-safe: concurrent
        callers get the same rig. Raises ``MonoTrackerError`` when it cannot be created."""
        rob = self.rig
        if rob is not None:
            return rob
        with self._create_lock:
            if self.rig is None:  # checked again: another caller may have created it meanwhile
                rob = rigs.make_robot_rig(self.cfg, self._session)
                with self._lock:
                    self.rig = rob
                if self.estop_without_robot:  # read after the rig is published (signal_estop: the reverse)
                    rob.estop()
                    self.loop.events.event("estop_latched_on_connect", "robot connected e-stopped: the e-stop "
                                           "pressed before it was connected is latched", level="warning")
                if self.threads_wanted and self.cfg.clock == "real":
                    rob.start_thread()
                plan = self.plan.copy()
                if plan.T_base_cam is None and rob.default_T_base_cam is not None:
                    self.plan.set_hand_eye(rob.default_T_base_cam)
        return self.rig

    def state(self) -> str:
        """The robot's state as last read: disarmed|armed|tracking|holding|estopped (estopped also
        while an e-stop pressed before any robot was connected is latched)."""
        with self._lock:
            if self.rig is None and self.estop_without_robot:
                return "estopped"
            return self._state

    def disarm_for_revision(self, why: str) -> None:
        """A plan revision (``why``) is about to be saved: an armed, tracking or holding robot is
        disarmed first, with the ``plan_changed_armed`` alarm (arming was consent to the plan as
        it was). Called under the session's state lock: takes only the rig's own locks."""
        rob = self.rig
        if rob is None:
            return
        st = rob.status().state
        if st not in ENGAGED:
            return
        r = rob.disarm()
        now_state = rob.status().state
        with self._lock:
            self._state = now_state
        msg = (f"the plan changed while the robot was {st} ({why}): "
               + ("robot disarmed" if r.ok else f"disarm refused ({r.message}), robot {now_state}")
               + "; arming is for one plan: arm again with the PIN")
        self.loop.alarms.persistent("plan_changed_armed", msg, {"why": why, "state": st, "disarmed": bool(r.ok)})

    def refresh(self) -> None:
        if self.rig is None:
            return
        st = self.rig.status()
        with self._lock:
            self._state = st.state
            was_conn, self._connected = self._connected, st.connected
            self._message = st.message
        if not st.connected and was_conn:
            self.loop.alert_once("robot_disconnected", "alarm", "robot_disconnected",
                             "robot connection lost; the arm controller stops the arm, tracking ended",
                             {"state": st.state})
        elif st.connected and not was_conn:
            self.loop.clear_alert("robot_disconnected")
            self.loop.alarms.alert("info", "robot_connected", "robot connection restored")
        self._sync_robot_alarms(st)
        self._audit_robot_states(st)

    def _audit_robot_states(self, st) -> None:
        """One ``robot_state`` audit row per state change, in the order the controller made them,
        each with the reason of its own transition (``engine/robot_transitions.py``); the rows
        follow each other (``from`` = the previous row's ``to``; ``monotracker audit verify``
        checks it). A rig that reports no transitions (a test double): the changes seen here."""
        events = self.loop.events
        with self._audit_lock:
            rows = self.rig.drain_transitions()
            if rows is None:
                if st.state == self._audited_state:
                    return
                from monotracker.engine.robot_transitions import RobotTransition

                rows = [RobotTransition(self._audited_state, st.state, st.message)]
            for tr in rows:
                if tr.from_state != self._audited_state:
                    # never expected (every transition is reported): say so rather than break the chain
                    events.event("robot_state", f"robot {self._audited_state} -> {tr.from_state} (a change the "
                                 "controller did not report)", {"from": self._audited_state, "to": tr.from_state,
                                                                "reason": "unreported", "t_control": None, "seq": None},
                                 level="warning")
                events.event("robot_state", f"robot {tr.from_state} -> {tr.to_state}" + (f" ({tr.reason})" if tr.reason else ""),
                             {"from": tr.from_state, "to": tr.to_state, "reason": tr.reason, "t_control": tr.t,
                              "seq": tr.seq})
                self._audited_state = tr.to_state

    def _sync_robot_alarms(self, st) -> None:
        """Active conditions that mirror the robot's state: e-stop latched, connection lost."""
        board, now = self.loop.alarms.board, self.now()
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
        why = self.plan.plan_not_ready()
        if why:
            return why
        rig, used = self.loop.camera.rig, self.loop.camera.rig_fiducials
        if rig is not None and rig.running and used is not None:
            now = self.plan.copy().fiducial_centres()
            if now.shape != used.shape or not np.array_equal(now, used):
                return "the fiducial set changed since the camera started; stop and start the camera"
        return None

    def arm(self, pin) -> CommandResult:
        """Arm the robot with the operator ``pin``. Refused: a wrong PIN or a lockout; the plan is
        not ready (:meth:`plan_not_ready`); a validation fiducial off by more than
        ``config.max_validation_tre_mm`` or not seen; no fresh trusted pose; the robot refuses.

        Order: the PIN (wrong tries count towards the lockout), the accuracy verification
        (validation fiducials; ``verification.json`` is written either way), then the plan and a
        fresh trusted pose (:meth:`_arm_robot`)."""
        if self.estop_without_robot or self.state() == "estopped":
            return self._refuse("arm", ESTOP_LATCHED)
        r = self._access.check_pin(pin, "arm_refused", "arming")
        if not r.ok:
            return r
        from monotracker.engine import verification

        why = verification.arm_refusal(self._session)
        try:
            verification.write_report(self._session, "refused" if why else "armed", why)
        except OSError as exc:
            self.loop.alarms.alert("warning", "verification_not_saved", f"verification report not saved: {exc}")
        if why:
            self.loop.alarms.alert("warning", "arm_refused", f"arming refused: {why}")
            return CommandResult(False, why)
        return self._arm_robot()

    def connect(self) -> CommandResult:
        """Connect the arm without arming it (it stays DISARMED)."""
        try:
            rob = self.ensure()
        except MonoTrackerError as exc:
            return CommandResult(False, str(exc))
        st = rob.status()
        return (CommandResult(True, "robot connected (disarmed)") if st.connected
                else CommandResult(False, f"robot not connected: {st.message}"))

    def _arm_robot(self) -> CommandResult:
        """Arm the robot (the PIN was checked); needs a fresh trusted pose registered for the
        current plan (see ``TrackingLoop.invalidate_pose``)."""
        why = self._plan_mismatch()
        if why:
            return self._refuse("arm", f"the plan is not ready: {why}")
        rec, _now, why = self.loop.wait_for_fresh_pose()
        if why is not None:
            return self._refuse("arm", f"no trusted, fresh pose for this plan ({why}); start the camera "
                                       "and wait for a valid pose")
        try:
            rob = self.ensure()
        except MonoTrackerError as exc:
            return CommandResult(False, str(exc))
        if self.estop_without_robot:
            return self._refuse("arm", ESTOP_LATCHED)
        r = rob.arm()
        self.refresh()
        if r.ok:
            self.loop.alarms.clear("plan_changed_armed")
        self.loop.events.event("arm" if r.ok else "arm_refused", "robot armed" if r.ok else f"arming refused: {r.message}",
                      level="info" if r.ok else "warning")
        return r

    def disarm(self) -> CommandResult:
        if self.rig is None:
            return CommandResult(True, "already disarmed")
        r = self.rig.disarm()
        self.refresh()
        self.loop.events.event("disarm", "robot disarmed" if r.ok else f"disarm refused: {r.message}")
        return r

    def start_tracking(self) -> CommandResult:
        """The arm follows the planned path as the head moves. Refused: not armed; the plan is not
        ready or changed since the camera started; no hand-eye; no trusted pose younger than
        ``config.max_pose_age_s`` (real clock: waits up to ``config.start_wait_s``)."""
        if self.rig is None or self.state() not in ("armed", "holding", "tracking"):
            return self._refuse("start_tracking", "arm the robot first")
        why = self._plan_mismatch()
        if why:
            return self._refuse("start_tracking", f"the plan is not ready: {why}")
        plan = self.plan.copy()
        if plan.T_base_cam is None:
            return self._refuse("start_tracking", "no hand-eye calibration (T_base_cam)")
        rec, now, why = self.loop.wait_for_fresh_pose(START_ARRIVAL_S if self.cfg.clock == "real" else None)
        if why is not None:
            return self._refuse("start_tracking", f"no trusted, fresh pose ({why})")
        if self.loop.holding_code in FRESHNESS_CODES:
            self.loop.resume("operator started tracking on a fresh pose", self.loop.registration_data(rec.sample))
        self.loop.push_target(rec.sample, now)
        r = self.rig.start_tracking()
        self.refresh()
        if r.ok:
            T_target = self.loop.target()[0]
            self.loop.events.event("tracking_started", "tracking started",
                                   {"registration": self.loop.registration_data(rec.sample),
                                    "T_base_target_mm": None if T_target is None else T_target.tolist()})
        else:
            self.loop.events.event("tracking_refused", f"tracking refused: {r.message}", level="warning")
        return r

    def _refuse(self, code: str, msg: str) -> CommandResult:
        self.loop.events.event(f"{code}_refused", f"{code.replace('_', ' ')} refused: {msg}", level="warning")
        return CommandResult(False, msg)

    def stop_tracking(self) -> CommandResult:
        if self.rig is None:
            return CommandResult(True, "not tracking")
        r = self.rig.stop_tracking()
        self.refresh()
        self.loop.events.event("tracking_stopped", "tracking stopped by the operator")
        return r

    def signal_estop(self) -> None:
        """The stop channel (``engine/pipeline_priority.py``): straight to the robot's controller,
        before anything else, without the loop's lock; never raises (a failure is logged; the
        full :meth:`estop` that follows reports it)."""
        rob = self.rig
        if rob is None:
            self.estop_without_robot = True  # latched: arming refused, a robot connected later starts e-stopped
            rob = self.rig  # connected meanwhile? (ensure() reads the latch after publishing the rig)
            if rob is None:
                return
        try:
            rob.signal_estop()
        except Exception:  # the STOP handler must survive; estop() says what failed
            log.exception("signalling the e-stop failed")

    def estop(self) -> CommandResult:
        """Signal the stop, wait (bounded) for the controller's acknowledgement, then record it.
        Without an acknowledgement the ``estop_unconfirmed`` alarm stands until a later stop is
        confirmed."""
        if self.rig is None:
            self.estop_without_robot = True
            if self.rig is None:
                msg = ("EMERGENCY STOP latched (no robot connected): arming is refused and a robot connected "
                       "now starts e-stopped; reset the e-stop to continue")
                self.loop.alarms.board.set("estop", msg, self.now())
                self.loop.alarms.alert("alarm", "estop", msg)
                return CommandResult(True, "e-stop latched (no robot connected)")
        r = self.rig.estop()  # signals first, then waits for the acknowledgement
        self.refresh()
        board, now = self.loop.alarms.board, self.now()
        if r.ok:
            board.clear("estop_unconfirmed", now)
            self.loop.alarms.alert("alarm", "estop", f"EMERGENCY STOP pressed; arm stopped and latched: {r.message}")
        else:
            board.set("estop_unconfirmed", r.message, now, level="alarm")
            self.loop.alarms.alert("alarm", "estop_unconfirmed", r.message)
        return r

    def reset_estop(self) -> CommandResult:
        if self.rig is None:
            if not self.estop_without_robot:
                return CommandResult(True, "nothing to reset")
            self.estop_without_robot = False
            self.loop.alarms.clear("estop")
            self.loop.events.event("estop_reset", "e-stop reset (no robot connected); robot disarmed")
            return CommandResult(True, "e-stop reset")
        r = self.rig.reset()
        if r.ok:
            self.estop_without_robot = False
        self.refresh()
        self.loop.events.event("estop_reset", "e-stop reset; robot disarmed" if r.ok else f"e-stop reset refused: {r.message}")
        return r

