"""RobotRig whose control loop runs in its own process (``robot.control_process``).

Used for ``clock="real"`` sessions when ``SessionConfig.control_process`` is on (the default):
the tracker, its safety layer and the arm backend live in a spawned child at elevated priority
where the OS allows, so vision, the web server and logging in the engine process cannot delay a
control cycle. The engine sees the same :class:`RobotStatus` as with the in-process rig
(``engine/rigs/robot.py``), plus ``control`` saying where the loop runs and with which priority.
``clock="sim"`` sessions keep the in-process, deterministic rig.
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from monotracker.engine.pipeline_priority import CONTROL_FALLBACK_NICE, CONTROL_FIFO_PRIORITY
from monotracker.engine.rigs.base import RobotStatus
from monotracker.engine.rigs.robot import TrackerRobotRig, arm_setup
from monotracker.engine.robot_transitions import TransitionLog
from monotracker.engine.snapshot import CommandResult
from monotracker.errors import MonoTrackerError
from monotracker.robot.tip_speed import TipSpeed

log = logging.getLogger(__name__)


class ProcessRobotRig(TrackerRobotRig):
    """Same interface and states as :class:`TrackerRobotRig`; the tracker runs in a child."""

    def __init__(self, cfg, session, opts: dict | None = None):  # no super().__init__: no local tracker
        from monotracker.robot.control_process import ControlProcess, ControlProcessError
        from monotracker.robot.kinematics import Kinematics, NeedleTool

        self.s = session
        self.clock = session.clock
        self.sim_arm = None  # lives in the child; its truth comes back through the state slot
        self.tracker = None
        self.transitions = TransitionLog()  # the child's reports, back in order (the audit's robot_state rows)
        self._exit_noted = False
        factory, self.default_T_base_cam, self._is_sim = arm_setup(cfg)
        self._kin, self._tool = Kinematics(), NeedleTool()
        # the only real-time code of the app (the priority policy: engine/pipeline_priority.py)
        opts = {"fifo_priority": CONTROL_FIFO_PRIORITY, "fallback_nice": CONTROL_FALLBACK_NICE, **(opts or {})}
        try:
            self.proc = ControlProcess(factory, {"variant": cfg.controller, "rate_hz": cfg.control_hz,
                                                 "predict_target": cfg.predict_target},
                                       on_event=self._on_event, opts=opts)
        except ControlProcessError as exc:
            raise MonoTrackerError(str(exc)) from None
        ok, reason = self.proc.connect_result
        if not ok:
            self.proc.close()
            raise MonoTrackerError(f"robot did not connect: {reason}")
        self.control = f"control process pid {self.proc.pid}, {self.proc.priority}"
        log.info("robot %s", self.control)
        if not self.proc.priority.startswith("SCHED_FIFO"):
            session.alert("warning", "control_priority", f"robot control process runs without real-time "
                                                         f"priority: {self.proc.priority}")
        session.record("control_process", self.control, {"pid": self.proc.pid, "priority": self.proc.priority})
        self._tip_speed = TipSpeed()
        self._head_ct: tuple[np.ndarray, float] | None = None
        self._status_cache = None
        self._status_lock = threading.Lock()

    # ------------------------------------------------------------------ commands
    def _cmd(self, name: str) -> CommandResult:
        ok, reason = self.proc.command(name)
        return CommandResult(bool(ok), str(reason))

    def arm(self) -> CommandResult:
        self._set_head_sphere()
        return self._cmd("arm")

    def disarm(self) -> CommandResult:
        return self._cmd("disarm")

    def start_tracking(self) -> CommandResult:
        return self._cmd("start_tracking")

    def stop_tracking(self) -> CommandResult:
        return self._cmd("stop_tracking")

    def estop(self) -> CommandResult:
        """Signal the stop and wait for the control process's acknowledgement (bounded)."""
        ok, reason = self.proc.estop("operator e-stop")
        self._status_cache = None
        return CommandResult(bool(ok), str(reason))

    def signal_estop(self) -> None:
        self.proc.signal_estop()

    def reset(self) -> CommandResult:
        ok, reason = self.proc.reset()
        self._status_cache = None
        return CommandResult(bool(ok), str(reason))

    def drain_transitions(self) -> list:
        return self.transitions.drain()

    def _controller(self):
        return self.proc  # same set_target / set_head_sphere as the in-process Tracker

    def step(self, now: float) -> None:
        raise MonoTrackerError("the control process runs on its own clock; step() is for clock='sim' sessions")

    def start_thread(self) -> None:
        pass  # the child's loop runs from the start

    def inject_disconnect(self) -> None:
        ok, reason = self.proc.command("drop")
        if not ok:
            raise MonoTrackerError(reason)

    def close(self) -> None:
        self.proc.close()

    # ------------------------------------------------------------------ state
    def _status(self) -> RobotStatus:
        st = self.proc.state()
        if st is None:
            return RobotStatus("disarmed", False, "not started", control=self.control)
        if not self.proc.alive:
            rep = self.proc.exit_report or {}
            msg = f"robot control process exited ({rep.get('reason') or 'exit code ' + str(self.proc.proc.exitcode)})"
            if not self._exit_noted:
                self._exit_noted = True  # a change the engine decides: no report from the child explains it
                self.transitions.add_local("estopped", msg)
            return RobotStatus("estopped", False, msg, control=self.control)
        key = (st.t_published, st.state, self.proc.live_state())
        if self._status_cache is not None and self._status_cache[0] == key:
            return self._status_cache[1]
        if self._is_sim and np.all(np.isfinite(st.true_q)):
            from monotracker.robot.units import transform_m_to_mm

            q, qd = st.true_q, st.true_dq
            T_tip = transform_m_to_mm(self._kin.fk(q) @ self._tool.T_tool0_tip)
        else:
            q, qd = st.q, st.dq
            T_tip = st.T_base_tip_mm if np.all(np.isfinite(st.T_base_tip_mm)) else None
        t_state = st.t_published
        speed = self._tip_speed.update(T_tip, t_state)
        stamp = st.target_stamp if np.isfinite(st.target_stamp) else None
        status = RobotStatus(state=self.proc.live_state(), connected=st.connected, message=self.proc.last_reason,
                             q=q, qd=qd, T_base_tip=T_tip, speed_mm_s=speed, command_stamp=stamp,
                             t_command=st.t, program_fault=st.program_fault, control=self.control)
        self._status_cache = (key, status)
        return status

    def status(self) -> RobotStatus:
        with self._status_lock:
            return self._status()

    # events from the child arrive as dicts
    def _on_event(self, kind: str, payload) -> None:
        try:
            if kind == "transition":
                self.transitions.add(payload["from"], payload["to"], payload["reason"], payload.get("t"),
                                     payload.get("seq"))
                self.s.record("robot_transition", f"robot {payload['from']} -> {payload['to']}: {payload['reason']}",
                              {"from": payload["from"], "to": payload["to"], "reason": payload["reason"],
                               "seq": payload.get("seq"), "t_control": payload.get("t")})
            elif kind == "warning":
                self.s.alert("warning", "robot_warning", str(payload))
        except Exception:
            log.exception("robot event forwarding failed")
