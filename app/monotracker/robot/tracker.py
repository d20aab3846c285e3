"""The robot tracker the engine uses: APFF controller + safety layer + arm backend.

Public units are millimetres (poses ``T_base_target_mm``: 4x4 with translation in mm, base =
UR10 ``base_link``); inside, metres (see :mod:`monotracker.robot.units`). The target is the
desired pose of the *needle tip* frame (z axis = needle direction, pointing into the head).

Two ways to run it:

* ``step(now)``: one control cycle at time ``now`` (s). Tests, benchmarks and the demo drive it
  with a simulated clock (:class:`~monotracker.robot.sim_arm.ManualClock`) shared with the
  :class:`~monotracker.robot.sim_arm.SimulatedArm`, deterministic and faster than real time.
* ``start()`` / ``stop()``: a real-time thread calling ``step`` at ``rate_hz`` (125 Hz for a
  CB3, 500 Hz for an e-Series).

``predict_target=True`` turns on :class:`TargetPredictor` (latency compensation and velocity
feed-forward from the pose stream; not in the paper, see ``benchmarks/robot_control.py`` for
what it buys).

Operator actions (``arm``, ``disarm``, ``start_tracking``, ``stop_tracking``, ``estop``,
``reset``) return a :class:`CommandResult` (``ok``, ``reason``) and never raise for expected
refusals. ``snapshot()`` is thread-safe. ``on_event(kind, payload)`` is called for
``"transition"`` (a :class:`~monotracker.robot.safety.Transition`) and ``"warning"`` (str); keep
it short, it runs in the control thread.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import Callable

import numpy as np

from monotracker.geometry import apply_transform
from monotracker.robot.apff import APFFController, APFFParams
from monotracker.robot.arm import Arm, ArmError, ArmProgramStopped
from monotracker.robot.head import Corridor, HeadSphere
from monotracker.robot.kinematics import Kinematics, NeedleTool, manipulability
from monotracker.robot.pacing import run_paced
from monotracker.robot.prediction import TargetPredictor  # re-exported: its old home
from monotracker.robot.safety import SafetyConfig, SafetyLayer, State, Transition
from monotracker.robot.tracker_snapshot import CommandResult, TrackerSnapshot  # their old home: here
from monotracker.robot.units import m_to_mm, mm_to_m, transform_m_to_mm, transform_mm_to_m

log = logging.getLogger(__name__)


class Tracker:
    """APFF controller + safety layer + arm backend (see the module docstring).

    Args:
        arm: the arm backend (:class:`~monotracker.robot.arm.Arm`); default a
            :class:`~monotracker.robot.sim_arm.SimulatedArm` on ``clock`` at ``rate_hz``.
        variant: ``"APF-V" | "APF-A-I" | "APF-A-II"`` (paper section 2.3).
        params: controller gains (:class:`APFFParams`, paper Eq. 32 defaults).
        safety_config: limits and timeouts (:class:`SafetyConfig`).
        tool: the needle (tip on tool0's z axis; default 0.20 m).
        corridor: the planned-path tube where head repulsion and keep-out are off.
        rate_hz: control rate (Hz; 125 for a UR CB3, 500 for an e-Series), > 0.
        clock: monotonic seconds; capture stamps must be on the same clock.
        on_event: ``(kind, payload)`` callback, ``"transition"`` / ``"warning"``; runs in the
            control thread.
        predict_target: latency compensation (:mod:`monotracker.robot.prediction`; off by default,
            see ``docs/robot.md`` for why).
        prediction_horizon_s: the prediction's extrapolation cap (s).

    Raises ``ValueError`` for ``rate_hz <= 0`` or an unknown variant."""

    #: how many cycle start times the real-time loop keeps (:attr:`cycle_starts`)
    CYCLE_LOG = 20000

    def __init__(self, arm: Arm | None = None, variant: str = "APF-A-II",
                 params: APFFParams | None = None, safety_config: SafetyConfig | None = None,
                 tool: NeedleTool | None = None, corridor: Corridor | None = None,
                 rate_hz: float = 125.0, clock: Callable[[], float] = time.monotonic,
                 on_event: Callable[[str, object], None] | None = None,
                 predict_target: bool = False, prediction_horizon_s: float = 0.15):
        if arm is None:
            from monotracker.robot.sim_arm import SimulatedArm

            arm = SimulatedArm(clock=clock, period_s=1.0 / rate_hz)
        if not (rate_hz > 0):
            raise ValueError("rate_hz must be > 0")
        self.arm_backend = arm
        self.clock = clock
        self.period = 1.0 / rate_hz
        self.tool = tool or NeedleTool()
        self.corridor = corridor or Corridor()
        self.on_event = on_event
        self.controller = APFFController(variant, params, self.tool, self.corridor)
        self.safety = SafetyLayer(safety_config, self.tool, self.corridor, on_transition=self._on_transition)
        self.kin = Kinematics()
        self._lock = threading.RLock()
        self._head_local: tuple[str, np.ndarray, float] | None = None
        self._last_t: float | None = None
        self._stopping_sent = False
        self._thread: threading.Thread | None = None
        self._run = threading.Event()
        self._n_warn = 0
        self._snap: TrackerSnapshot | None = None
        self._controller_reset_due = False
        self._program_fault: ArmProgramStopped | None = None
        #: real-time thread: cycles that ended after the next deadline, and the slowest cycle (ms)
        self.overruns = 0
        self.worst_cycle_ms = 0.0
        self.predictor = TargetPredictor(prediction_horizon_s) if predict_target else None
        #: real-time thread: start time (clock s) of the latest cycles (period jitter; benchmarks)
        self.cycle_starts: deque = deque(maxlen=self.CYCLE_LOG)

    # ------------------------------------------------------------------ events
    def _on_transition(self, tr: Transition) -> None:
        if tr.to_state != State.TRACKING:
            # Reset in the control thread (next step), not here: an e-stop can transition from
            # another thread while the controller is mid-step.
            self._controller_reset_due = True
        if self.on_event:
            try:
                self.on_event("transition", tr)
            except Exception:
                log.exception("tracker event callback failed")

    def _emit_warnings(self) -> None:
        while self._n_warn < len(self.safety.warnings):
            w = self.safety.warnings[self._n_warn]
            self._n_warn += 1
            if self.on_event:
                try:
                    self.on_event("warning", w)
                except Exception:
                    log.exception("tracker event callback failed")

    @property
    def state(self) -> State:
        return self.safety.state

    @property
    def variant(self) -> str:
        return self.controller.variant

    # ------------------------------------------------------------------ connection / operator
    def connect(self) -> CommandResult:
        """Open (or re-open) the arm connection. Returns ``CommandResult``; refused (ok=False,
        one line) when the arm does not answer or its control program is stopped (then only
        :meth:`reset` restarts it). Never resumes motion: if the link is down
        while armed/tracking/holding (a drop the control loop may not have seen yet), the e-stop
        latches first; if it is up, there is nothing to do."""
        with self._lock:
            if self.safety.state in (State.ARMED, State.TRACKING, State.HOLDING):
                try:
                    up = bool(self.arm_backend.is_connected())
                except Exception:  # noqa: BLE001
                    up = False
                if up:
                    return CommandResult(True, "already connected")
                self.safety.estop(self.clock(), "arm connection lost (reconnect requested)")
                self._stop_arm(self.safety.cfg.estop_decel)
        try:
            self.arm_backend.connect()
        except ArmError as exc:
            return CommandResult(False, str(exc))
        return CommandResult(True, "connected")

    def disconnect(self) -> None:
        """Stop the loop thread (if running), disarm, stop the arm and close the connection.
        Never raises; an e-stop stays latched."""
        self.stop()
        with self._lock:
            if self.safety.state not in (State.DISARMED, State.ESTOPPED):
                self.safety.disarm(self.clock(), "tracker disconnected")
            self.arm_backend.disconnect()

    def arm(self) -> CommandResult:
        """Operator action: disarmed -> armed (the arm holds still, commands stay zero).
        Refused (ok=False, reason) when not disarmed (e.g. e-stopped: reset first) or the arm
        is not connected."""
        with self._lock:
            return CommandResult(*self.safety.arm(self.clock(), self.arm_backend.is_connected()))

    def disarm(self) -> CommandResult:
        """Operator action: armed/tracking/holding -> disarmed (the arm decelerates to rest).
        Refused when e-stopped (reset leaves the e-stop) or already disarmed."""
        with self._lock:
            return CommandResult(*self.safety.disarm(self.clock()))

    def start_tracking(self) -> CommandResult:
        """Operator action: armed/holding -> tracking. Refused (ok=False, reason) when not armed
        or holding, or without a fresh valid target (capture stamp within the safety layer's
        freshness limits). Tracking without a head sphere is allowed (the sphere may be
        unknown, e.g. too few fiducials for the fit) but warned about: then neither the keep-out
        nor the APF repulsion can act."""
        with self._lock:
            res = CommandResult(*self.safety.start_tracking(self.clock()))
            if res.ok and self._head_local is None:
                msg = "tracking with no head sphere: keep-out and head repulsion are off"
                log.warning(msg)
                self.safety.warnings.append(msg)
                self._emit_warnings()
            return res

    def stop_tracking(self) -> CommandResult:
        """Operator action: tracking/holding -> armed (the arm decelerates to rest and stays
        there; tracking never resumes by itself after this). Refused when not tracking/holding."""
        with self._lock:
            return CommandResult(*self.safety.stop_tracking(self.clock()))

    #: How long :meth:`estop` waits for a control cycle in progress before giving up on sending
    #: the stop itself (s). The e-stop is latched before waiting either way.
    ESTOP_LOCK_WAIT_S = 0.05

    def estop(self, reason: str = "operator e-stop") -> CommandResult:
        """Latched stop, effective immediately (``reason``: one line for the log and the UI;
        always returns ok=True): the state latches at once (without waiting for
        the control loop), then the arm is told to stop. If a control cycle is stuck in an arm
        call, the stop is left to that cycle (it re-checks the state after sending a command)
        and, should the call never return, to the arm's own watchdog. Never blocks for long."""
        self.safety.estop(self.clock(), reason)
        if self._lock.acquire(timeout=self.ESTOP_LOCK_WAIT_S):
            try:
                self._stop_arm(self.safety.cfg.estop_decel)
            finally:
                self._lock.release()
        else:
            log.error("e-stop latched while the control loop is busy in an arm call; "
                      "the loop stops the arm when the call returns (the arm watchdog if it never does)")
        return CommandResult(True, "e-stopped")

    def reset(self) -> CommandResult:
        """Operator action: leave the e-stop (to disarmed; arming again is another action).
        If the arm's control program has stopped (a UR's script: watchdog, pendant stop,
        protective stop), this is the one place it is restarted (:meth:`Arm.recover`, e.g.
        ``reuploadScript``); never while armed, never by itself. Refused with a one-line reason
        when the restart fails (e.g. a protective stop not yet cleared on the pendant)."""
        with self._lock:
            if self.safety.state != State.ESTOPPED:
                return CommandResult(*self.safety.reset(self.clock()))
            try:
                fault = self.arm_backend.program_fault()
                if fault is not None:
                    self.arm_backend.recover()
                    log.info("arm control program restarted on reset (was: %s)", fault)
            except ArmError as exc:
                return CommandResult(False, f"reset refused: {exc}")
            except Exception as exc:  # never a traceback to the operator
                log.exception("arm recovery failed")
                return CommandResult(False, f"reset refused: arm recovery failed ({type(exc).__name__}: {exc})")
            self._program_fault = None
            return CommandResult(*self.safety.reset(self.clock()))

    # ------------------------------------------------------------------ inputs
    def set_target(self, T_base_target_mm: np.ndarray, stamp: float, valid: bool = True,
                   now: float | None = None) -> CommandResult:
        """New desired needle-tip pose from one camera frame.

        Args:
            T_base_target_mm: (4, 4) rigid transform, base frame -> needle-tip target frame,
                translation in mm; z axis along the planned path into the head.
            stamp: capture time of the frame it was measured from (s, the tracker's clock).
            valid: False when the pose stream has no pose (e.g. fiducials occluded): holds.
            now: time of arrival (s); default the tracker clock.

        Returns ``CommandResult``: ok=False with the reason when refused (NaN or non-rigid pose,
        no finite stamp, too old, a stamp in the future, a jump > 20 mm / 10 deg, invalid); a
        refused target holds the arm (auto-resume or operator restart, see the safety layer)
        and resets the latency prediction. Never raises."""
        with self._lock:
            now = self.clock() if now is None else now
            try:
                T = transform_mm_to_m(np.asarray(T_base_target_mm, dtype=float))
            except (ValueError, TypeError, IndexError):
                T = np.full((4, 4), np.nan)
            if T.shape != (4, 4):
                T = np.full((4, 4), np.nan)
            try:
                stamp = float(stamp)
            except (TypeError, ValueError):
                stamp = float("nan")  # refused (and held) by the safety layer
            st = self.safety.check_target(T, stamp, bool(valid), now)
            if self.predictor is not None:
                if st.accepted:
                    self.predictor.update(T, stamp)
                else:
                    self.predictor.reset()
            return CommandResult(st.accepted, st.reason)

    def set_head_sphere(self, centre_mm: np.ndarray, radius_mm: float, frame: str = "target") -> CommandResult:
        """Head obstacle (e.g. from :func:`~monotracker.robot.head.fit_head_sphere`).

        Args:
            centre_mm: (3,) sphere centre, mm, in ``frame``.
            radius_mm: sphere radius, mm, > 0.
            frame: ``"target"``: centre in the needle-tip target frame, so the sphere moves with
                the head; ``"base"``: fixed in the robot base frame.

        Returns ``CommandResult``; refused (ok=False) for a non-finite centre, a radius <= 0 or
        an unknown frame (the previous sphere is kept)."""
        c = np.asarray(centre_mm, dtype=float).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)) or not (np.isfinite(radius_mm) and radius_mm > 0):
            return CommandResult(False, "head sphere needs a finite centre (3 values, mm) and radius > 0 mm")
        if frame not in ("target", "base"):
            return CommandResult(False, f"head sphere frame must be 'target' or 'base', not {frame!r}")
        with self._lock:
            self._head_local = (frame, mm_to_m(c), float(mm_to_m(radius_mm)))
        return CommandResult(True, "head sphere set")

    def clear_head_sphere(self) -> None:
        """Forget the head obstacle (keep-out and repulsion off; tracking then warns)."""
        with self._lock:
            self._head_local = None

    def head_sphere_base(self) -> HeadSphere | None:
        """Current head sphere in the base frame (m), or None."""
        if self._head_local is None:
            return None
        frame, c, r = self._head_local
        if frame == "target":
            if self.safety.target is None:
                return None
            c = apply_transform(self.safety.target, c)
        return HeadSphere(np.asarray(c), r)

    # ------------------------------------------------------------------ control cycle
    def _stop_arm(self, decel: float) -> None:
        try:
            self.arm_backend.stop(decel)
        except Exception:  # stopping must never raise
            log.exception("arm stop failed")

    def _stop_decel(self) -> float:
        """Deceleration (rad/s^2) for the current non-tracking state: the e-stop's, else the
        joint acceleration limit."""
        return self.safety.cfg.estop_decel if self.safety.state == State.ESTOPPED else self.safety.cfg.joint_accel

    def step(self, now: float | None = None) -> TrackerSnapshot:
        """One control cycle at time ``now`` (s, the tracker's clock; default: now). Reads the
        arm, runs controller and safety filter, commands or stops the arm. Returns the
        :class:`TrackerSnapshot`; never raises (any fault latches the e-stop)."""
        t0 = time.perf_counter()
        with self._lock:
            now = self.clock() if now is None else float(now)
            dt = self.period if self._last_t is None else float(np.clip(now - self._last_t, 0.25 * self.period, 4 * self.period))
            backwards = self._last_t is not None and now < self._last_t - self.period
            if backwards:  # every age would be negative: stale targets would look fresh
                self.safety.estop(now, f"control clock went backwards by {self._last_t - now:.3f} s")
            self._last_t = now
            q = dq = cmd = np.full(6, np.nan)
            T = np.full((4, 4), np.nan)
            stage, smin = "-", float("nan")
            connected = False
            head = None
            try:
                connected = bool(self.arm_backend.is_connected())
                if not connected:
                    if self.safety.state not in (State.DISARMED, State.ESTOPPED):
                        self.safety.estop(now, "arm connection lost")
                        self._stop_arm(self.safety.cfg.estop_decel)
                else:
                    st = self.arm_backend.read()
                    self._program_fault = None
                    q, dq = st.q, st.dq
                    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(dq))):
                        raise ArmError("arm reported non-finite joint state")
                    T, Jb = self.kin.fk_and_jacobian_body(q)
                    head = self.head_sphere_base()
                    if self._controller_reset_due:
                        self._controller_reset_due = False
                        self.controller.reset()
                    self.controller.head = head
                    if self.predictor is not None and self.safety.state != State.TRACKING:
                        self.predictor.reset()  # holding/armed/...: no velocity survives a stop
                    if self.safety.state == State.TRACKING and self.safety.target is not None:
                        T_goal, V_goal = self.safety.target, None
                        if self.predictor is not None:
                            T_goal, V_goal = self.predictor.predict(T_goal, now)
                        out = self.controller.step(T, Jb, dq, T_goal, dt, V_goal)
                        dq_des, smin, stage = out.dq, out.sigma_min, out.stage
                    else:
                        dq_des = np.zeros(6)
                        smin = manipulability(Jb)
                    cmd = self.safety.filter_command(now, q, dq_des, dt, T, Jb, smin, head)
                    if cmd is None:
                        decel = self._stop_decel()
                        self.arm_backend.stop(decel)
                        cmd = np.zeros(6)
                    else:
                        self.arm_backend.command_velocity(cmd, self.safety.cfg.joint_accel)
                        if self.safety.state != State.TRACKING:
                            # latched (e-stop) from another thread while the command was sent
                            self._stop_arm(self._stop_decel())
            except ArmError as exc:
                if isinstance(exc, ArmProgramStopped):
                    self._program_fault = exc
                self.safety.estop(now, f"arm error: {exc}")
                self._stop_arm(self.safety.cfg.estop_decel)
                try:  # the error may have been the link dropping: report it in the snapshot
                    connected = bool(self.arm_backend.is_connected())
                except Exception:  # noqa: BLE001
                    connected = False
            except Exception as exc:  # any fault in the loop stops the arm
                log.exception("control loop error")
                self.safety.estop(now, f"internal error in control loop: {type(exc).__name__}: {exc}")
                self._stop_arm(self.safety.cfg.estop_decel)
            self._emit_warnings()
            snap = self._make_snapshot(now, connected, q, dq, cmd, T, stage, smin, (time.perf_counter() - t0) * 1e3, head)
            self._snap = snap
            return snap

    def _make_snapshot(self, now, connected, q, dq, cmd, T, stage, smin, cost_ms, head=None) -> TrackerSnapshot:
        tgt = self.safety.target
        T_tip = T @ self.tool.T_tool0_tip
        if tgt is not None and np.all(np.isfinite(T)):
            err = float(m_to_mm(np.linalg.norm(T_tip[:3, 3] - tgt[:3, 3])))
            c = float(np.clip(T_tip[:3, 2] @ tgt[:3, 2], -1.0, 1.0))
            ang = float(np.degrees(np.arccos(c)))
        else:
            err = ang = float("nan")
        hist = self.safety.history
        return TrackerSnapshot(
            t=now, state=self.safety.state.value, connected=connected,
            variant=self.controller.variant, q=np.array(q), dq=np.array(dq), dq_cmd=np.array(cmd),
            T_base_tool0_mm=transform_m_to_mm(T), T_base_tip_mm=transform_m_to_mm(T_tip),
            T_base_target_mm=None if tgt is None else transform_m_to_mm(tgt),
            tip_error_mm=err, angle_error_deg=ang,
            target_age_s=float(now - self.safety.target_received) if tgt is not None else float("inf"),
            stage=stage, sigma_min=smin, last_transition=hist[-1] if hist else None,
            warnings=tuple(self.safety.warnings[-5:]), step_cost_ms=cost_ms, overruns=self.overruns,
            keepout_active=head is not None,
            program_fault="" if self._program_fault is None else self._program_fault.cause,
            program_fault_reason="" if self._program_fault is None else str(self._program_fault),
        )

    def snapshot(self) -> TrackerSnapshot | None:
        """Latest snapshot (thread-safe without the loop's lock: the snapshot is immutable and
        replaced whole, so a UI never waits behind a control cycle; None before the first step)."""
        return self._snap

    # ------------------------------------------------------------------ real-time thread
    def start(self) -> None:
        """Run :meth:`step` at ``rate_hz`` in a daemon thread (real clock), paced by the arm's
        own ``begin_cycle``/``wait_cycle`` (ur_rtde ``initPeriod``/``waitPeriod``) when it has
        them. For a loop no other work in the process can stall, see
        :mod:`monotracker.robot.control_process`."""
        if self._thread and self._thread.is_alive():
            return
        self._run.set()
        self._thread = threading.Thread(target=self._loop, name="robot-tracker", daemon=True)
        self._thread.start()

    def _report_overrun(self, late_s: float) -> None:
        """Count a cycle that ended ``late_s`` after its deadline; warn on the first and every
        100th (the warning goes through the safety layer's list, so snapshots show it too)."""
        self.overruns += 1
        if self.overruns == 1 or self.overruns % 100 == 0:
            msg = (f"control loop overran its {self.period * 1e3:.1f} ms period "
                   f"({self.overruns} cycles so far, this one {late_s * 1e3:.1f} ms late, "
                   f"slowest {self.worst_cycle_ms:.1f} ms)")
            log.warning(msg)
            with self._lock:
                self.safety.warnings.append(msg)
                self._emit_warnings()

    def _loop(self) -> None:
        run_paced(self, self._run.is_set, self._thread_cycle)

    def _thread_cycle(self, t_start: float) -> None:
        try:
            self.step()
        except Exception as exc:  # step() catches loop errors; this is the last guard
            log.exception("tracker thread error")
            with self._lock:
                self.safety.estop(self.clock(), f"internal error in tracker thread: {type(exc).__name__}: {exc}")
                self._stop_arm(self.safety.cfg.estop_decel)

    def _begin_cycle(self):
        try:
            return self.arm_backend.begin_cycle()
        except Exception:  # noqa: BLE001 - pacing falls back to our own sleep
            return None

    def _wait_cycle(self, token) -> bool:
        """The backend's own pacing (ur_rtde ``waitPeriod``) when it has one; False: sleep here."""
        try:
            return bool(self.arm_backend.wait_cycle(token))
        except Exception:  # noqa: BLE001
            return False

    def stop(self) -> None:
        """Stop the thread; the arm is left stopped (tracking ends, the state machine keeps
        its latched states)."""
        self._run.clear()
        if self._thread:
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():
                # Stuck in an arm call: the loop is no longer in control. Latch an e-stop
                # (lock-free) and do not wait behind the call; the arm's watchdog stops it
                # if the call never returns, the loop's own re-check if it does.
                log.error("tracker thread did not stop within 2 s (stuck in an arm call)")
                self.estop("tracker thread stuck in an arm call")
                return
        with self._lock:
            if self.safety.state in (State.TRACKING, State.HOLDING):
                self.safety.stop_tracking(self.clock(), "tracker thread stopped")
            self._stop_arm(self.safety.cfg.joint_accel)
