"""RobotRig on ``monotracker.robot``'s :class:`Tracker` (APFF controller + safety layer + arm).

The arm comes from the robot-backend table (``robot/backends.py``): robot="sim", a
``SimulatedArm`` on the session clock, started at the OR layout's standby configuration (needle
tip ``standby_mm`` = 60 mm back from the planned entry along the path, so the first approach is
short and straight); robot="ur:<ip>", the ur_rtde backend.

The tracker's own safety layer keeps its checks (stale target, jump, joint/tool speed limits,
keep-out); the engine's gate runs before it. The head obstacle for the APFF repulsion is a sphere
fitted (RANSAC, ``robot.head.fit_head_sphere``) to the plan's fiducials, expressed in the needle
target frame so that it moves with the head.
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from monotracker.engine.rigs.base import RobotRig, RobotStatus
from monotracker.engine.robot_transitions import TransitionLog
from monotracker.engine.snapshot import CommandResult
from monotracker.errors import MonoTrackerError
from monotracker.geometry import apply_transform, invert_transform
from monotracker.robot.tip_speed import TipSpeed

log = logging.getLogger(__name__)

STANDBY_MM = 60.0


def standby_configuration(layout, standby_mm: float = STANDBY_MM):
    """Joint angles (rad) with the needle tip ``standby_mm`` back from the planned entry on the
    path's axis (true head at rest), or None if the UR10 cannot reach it."""
    from monotracker.robot.targets import reachable

    T = layout.planned_needle_pose().copy()
    T[:3, 3] -= standby_mm * T[:3, 2]
    res = reachable(T)
    return res.q if res.ok else None


def arm_setup(cfg) -> tuple:
    """The arm of ``cfg.robot`` from the backend table (both rigs, in-process and control process):
    ``(picklable arm factory, T_base_cam of the OR layout (mm) or None, simulated)``. A simulated
    arm starts at the layout's standby configuration (its factory also takes ``clock=``).
    ``cfg.control_hz`` is the arm's rate (125 Hz for a CB3, 500 for an e-Series: RTDE frequency
    and speedJ time). Raises ``MonoTrackerError`` when the backend is not installed or the UR10
    cannot reach the standby pose."""
    from monotracker.robot.backends import arm_factory, parse_spec

    backend, _arg = parse_spec(cfg.robot)
    q0 = T_base_cam = None
    if backend.simulated:
        from monotracker.sim.or_layout import default_layout

        layout = default_layout()
        q0 = standby_configuration(layout)
        if q0 is None:
            raise MonoTrackerError("the OR layout's standby pose is not reachable by the UR10 (IK failed)")
        T_base_cam = layout.T_base_cam
    try:
        factory = arm_factory(cfg.robot, rate_hz=cfg.control_hz, seed=cfg.seed, q0=q0)
    except ImportError as exc:
        raise MonoTrackerError(f"the {backend.kind} arm backend is not available: {exc}") from exc
    return factory, T_base_cam, backend.simulated


class TrackerRobotRig(RobotRig):
    def __init__(self, cfg, session):
        from monotracker.robot.tracker import Tracker

        self.s = session
        self.clock = session.clock
        self._events: list = []
        self.transitions = TransitionLog(clock=session.clock)  # the audit's robot_state rows, in order
        factory, self.default_T_base_cam, simulated = arm_setup(cfg)
        arm = factory(clock=self.clock) if simulated else factory()
        self.sim_arm = arm if simulated else None
        delay, tau = getattr(arm, "delay_s", None), getattr(arm, "tau_s", None)
        self._response_s = None if delay is None or tau is None else float(delay + tau)
        self.tracker = Tracker(arm, variant=cfg.controller, clock=self.clock, rate_hz=cfg.control_hz,
                               on_event=self._on_event, predict_target=cfg.predict_target)
        r = self.tracker.connect()
        if not r.ok:
            raise MonoTrackerError(f"robot did not connect: {r.reason}")
        self._tip_speed = TipSpeed()
        self._head_ct: tuple[np.ndarray, float] | None = None
        self._status_cache = None
        self._status_lock = threading.Lock()
        self.tracker.step(self.clock())

    # ------------------------------------------------------------------ events from the tracker
    def _on_event(self, kind: str, payload) -> None:
        # runs on the control thread: keep it short, publish through the session bus
        try:
            if kind == "transition":
                self.transitions.add(payload.from_state.value, payload.to_state.value, payload.reason, payload.t,
                                     payload.seq)
                self.s.record("robot_transition", f"robot {payload.from_state.value} -> {payload.to_state.value}: "
                              f"{payload.reason}", {"from": payload.from_state.value, "to": payload.to_state.value,
                                                    "reason": payload.reason, "seq": payload.seq})
            elif kind == "warning":
                self.s.alert("warning", "robot_warning", str(payload))
        except Exception:
            log.exception("robot event forwarding failed")

    # ------------------------------------------------------------------ commands
    @staticmethod
    def _r(res) -> CommandResult:
        return CommandResult(bool(res.ok), str(res.reason))

    def arm(self) -> CommandResult:
        self._set_head_sphere()
        return self._r(self.tracker.arm())

    def disarm(self) -> CommandResult:
        return self._r(self.tracker.disarm())

    def start_tracking(self) -> CommandResult:
        return self._r(self.tracker.start_tracking())

    def stop_tracking(self) -> CommandResult:
        return self._r(self.tracker.stop_tracking())

    def estop(self) -> CommandResult:
        return self._r(self.tracker.estop("operator e-stop"))

    def signal_estop(self) -> None:
        # in-process: the tracker latches the state lock-free and stops the arm (its lock is
        # waited for at most Tracker.ESTOP_LOCK_WAIT_S)
        self.tracker.estop("operator e-stop")

    def drain_transitions(self) -> list:
        return self.transitions.drain()

    def reset(self) -> CommandResult:
        return self._r(self.tracker.reset())

    def set_target(self, T_base_target_mm, stamp: float, valid: bool, T_base_ct=None) -> None:
        if T_base_target_mm is None:
            T_base_target_mm = np.full((4, 4), np.nan)
        if valid and T_base_ct is not None and self._head_ct is not None:
            # the head sphere in the needle-target frame of THIS target (roll included)
            c_ct, r = self._head_ct
            c_target = apply_transform(invert_transform(np.asarray(T_base_target_mm, float)),
                                       apply_transform(np.asarray(T_base_ct, float), c_ct))
            self._controller().set_head_sphere(c_target, r, frame="target")
        self._controller().set_target(np.asarray(T_base_target_mm, float), float(stamp), bool(valid))

    def _controller(self):
        """What runs the tracker: here the in-process :class:`~monotracker.robot.tracker.Tracker`
        (the control process's proxy in :class:`~monotracker.engine.rigs.robot_process.ProcessRobotRig`)."""
        return self.tracker

    def _set_head_sphere(self) -> None:
        """Fit the head sphere (CT mm) to the plan's fiducials; placed with each target."""
        if self._head_ct is not None:
            return
        try:
            from monotracker.robot.head import fit_head_sphere

            plan = self.s.plan_copy()
            if not plan.path_complete:
                return
            fit = fit_head_sphere(plan.fiducial_centres())
            if not fit.ok:
                self.s.alert("warning", "head_sphere", f"{fit.reason}; APFF head repulsion off")
                return
            self._head_ct = (np.asarray(fit.centre_mm, float), float(fit.radius_mm))
            self.s.record("head_sphere", f"head obstacle: sphere of radius {fit.radius_mm:.0f} mm fitted to "
                          f"the fiducials ({fit.reason})", {"centre_ct_mm": fit.centre_mm, "radius_mm": fit.radius_mm})
        except Exception:  # the obstacle is an aid, not a precondition
            log.exception("head sphere setup failed")

    # ------------------------------------------------------------------ control
    def step(self, now: float) -> None:
        self.tracker.step(now)
        if self.sim_arm is not None:
            self.sim_arm.advance_to(now)  # the arm's physics runs on, also when disconnected
        self._status_cache = None

    def start_thread(self) -> None:
        self.tracker.start()

    def inject_disconnect(self) -> None:
        if self.sim_arm is None:
            raise MonoTrackerError("only the simulated arm can simulate a disconnect")
        self.sim_arm.drop_connection()

    def close(self) -> None:
        try:
            self.tracker.stop()
        finally:
            try:
                self.tracker.arm_backend.disconnect()
            except Exception:
                log.exception("arm disconnect failed")

    def status(self) -> RobotStatus:
        """Robot state; for the simulated arm, q/qd/tip are the arm's TRUE state (the twin's truth,
        also after a disconnect, when the tracker can no longer read the arm). Thread-safe."""
        with self._status_lock:
            return self._status()

    def _status(self) -> RobotStatus:
        snap = self.tracker.snapshot()
        if snap is None:
            return RobotStatus("disarmed", False, "not started")
        now = float(self.clock())
        key = (now, self.tracker.state.value)  # a command at the same instant changes the state
        if self._status_cache is not None and self._status_cache[0] == key:
            return self._status_cache[1]
        if self.sim_arm is not None:
            from monotracker.robot.units import transform_m_to_mm

            q, qd = self.sim_arm.true_q.copy(), self.sim_arm.true_dq.copy()
            T_tip = transform_m_to_mm(self.tracker.kin.fk(q) @ self.tracker.tool.T_tool0_tip)
            t_state = now
        else:
            q, qd = snap.q, snap.dq
            T_tip = snap.T_base_tip_mm if np.all(np.isfinite(snap.T_base_tip_mm)) else None
            t_state = snap.t
        speed = self._tip_speed.update(T_tip, t_state)
        msg = snap.last_transition.reason if snap.last_transition is not None else ""
        if snap.program_fault and snap.state == "estopped":
            msg = snap.program_fault_reason
        safety = self.tracker.safety
        stamp = safety.target_stamp if np.isfinite(safety.target_stamp) else None
        # the state machine's live state (the snapshot is from the last control step)
        st = RobotStatus(state=self.tracker.state.value, connected=bool(self.tracker.arm_backend.is_connected()),
                         message=msg, q=q, qd=qd, T_base_tip=T_tip, speed_mm_s=speed, command_stamp=stamp,
                         t_command=snap.t, program_fault=snap.program_fault,
                         control="in-process thread" if self.tracker._thread is not None else "in-process, stepped",
                         response_s=self._response_s)
        self._status_cache = (key, st)
        return st
