"""The child side of :mod:`monotracker.robot.control_process`: the real-time priority request
and the control loop process (:class:`_Child`) that owns the :class:`Tracker` and the arm."""

from __future__ import annotations

import gc
import json
import logging
import os
import queue
import threading
import time

import numpy as np

from monotracker.robot.control_layout import _OFF, PROGRAM_FAULTS, STATE_N, STATES
from monotracker.robot.pacing import run_paced

log = logging.getLogger(__name__)

#: joint speed (rad/s, every joint) under which the arm counts as standing still after a STOP
STILL_RAD_S = 1e-3


def elevate_priority(fifo_priority: int = 10, fallback_nice: int = -10) -> str:
    """Ask for SCHED_FIFO (``fifo_priority``), else nice ``fallback_nice`` (skipped when >= 0);
    returns what the OS allowed, in words (with the refusal's reason)."""
    why = []
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(fifo_priority)))
        return f"SCHED_FIFO priority {fifo_priority}"
    except (AttributeError, PermissionError, OSError) as exc:
        why.append(f"SCHED_FIFO refused ({exc.__class__.__name__}: {exc})")
    if int(fallback_nice) < 0:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, int(fallback_nice))
            return f"nice {int(fallback_nice)}; " + why[0]
        except (AttributeError, PermissionError, OSError) as exc:
            why.append(f"nice {int(fallback_nice)} refused ({exc.__class__.__name__})")
    return "normal priority; " + "; ".join(why)


class _Child:
    """Runs in the control process. See the module docstring."""

    def __init__(self, arm_factory, tracker_kwargs, conn, target_slot, state_slot, heart_slot, estop_ev,
                 parent_pid, opts, stop_slot=None):
        from monotracker.robot.tracker import Tracker

        self.conn = conn
        self.target_slot, self.state_slot, self.heart_slot = target_slot, state_slot, heart_slot
        self.estop_ev = estop_ev
        self.stop_slot = stop_slot  # the engine's stop requests: [number, time signalled]
        self._ack = (0, float("nan"))  # (newest stop request latched, when), published with the state
        self._still_t = float("nan")  # first cycle with the arm standing still after that stop
        self._pub_lock = threading.Lock()
        self.parent_pid = parent_pid
        self.opts = opts
        self.clock = time.monotonic
        self.outbox: queue.SimpleQueue = queue.SimpleQueue()
        arm = arm_factory()
        self.sim_arm = arm if hasattr(arm, "true_q") else None
        self.tracker = Tracker(arm, clock=self.clock, on_event=self._on_event, **tracker_kwargs)
        self.period = self.tracker.period
        self._seen_target = 0.0
        self._target_lock = threading.Lock()  # the slot is applied by the cycle and before a start
        self._parent_gone = threading.Event()
        self._quit = threading.Event()
        self._heart_lost = False
        self.starts = self.tracker.cycle_starts  # the same bounded log as the in-process loop
        self.cycles = 0
        self.exit_reason = ""

    # ------------------------------------------------------------------ events out (sender thread)
    def _on_event(self, kind, payload):
        if kind == "transition":
            payload = {"from": payload.from_state.value, "to": payload.to_state.value, "reason": payload.reason,
                       "t": payload.t, "seq": payload.seq}
        else:
            payload = str(payload)
        self.outbox.put(("event", kind, payload))

    def _sender(self):
        while True:
            msg = self.outbox.get()
            if msg is None:
                return
            try:
                self.conn.send(msg)
            except (OSError, EOFError, ValueError):
                self._parent_gone.set()
                return

    # ------------------------------------------------------------------ commands in (command thread)
    def _commands(self):
        tr = self.tracker
        while not self._quit.is_set():
            try:
                msg = self.conn.recv()
            except (EOFError, OSError):
                self._parent_gone.set()
                return
            cid, name, args = msg
            try:
                if name == "shutdown":
                    self.exit_reason = "engine asked the control process to stop"
                    self._quit.set()
                    res = (True, "stopping")
                elif name == "estop":  # the stop channel's second route: (reason, request number)
                    res = tr.estop(args[0] if args else "operator e-stop")
                    if len(args) > 1:
                        self._acknowledge(int(args[1]))
                elif name in ("arm", "disarm", "start_tracking", "stop_tracking", "reset", "connect"):
                    if name == "start_tracking":
                        # the engine writes the target it checked, then sends the start: judge
                        # the start on that target, not on one the next cycle has not applied yet
                        self._apply_target(self.clock())
                    res = getattr(tr, name)()
                elif name == "set_head_sphere":
                    res = tr.set_head_sphere(*args)
                elif name == "clear_head_sphere":
                    tr.clear_head_sphere()
                    res = (True, "cleared")
                elif name == "drop":
                    if self.sim_arm is None:
                        res = (False, "only the simulated arm can simulate a disconnect")
                    else:
                        self.sim_arm.drop_connection()
                        res = (True, "dropped")
                elif name == "cycle_starts":
                    res = (True, np.array(self.starts, dtype=float))
                elif name == "info":
                    res = (True, {"pid": os.getpid(), "priority": self.priority})
                else:
                    res = (False, f"unknown control command {name!r}")
                ok, reason = (res.ok, res.reason) if hasattr(res, "ok") else res
            except Exception as exc:  # a command never kills the control process
                log.exception("control command %s failed", name)
                ok, reason = False, f"{name} failed: {type(exc).__name__}: {exc}"
            self._publish(self.clock())  # the reply's effect is visible once the reply arrives
            self.outbox.put(("reply", cid, bool(ok), reason))

    # ------------------------------------------------------------------ e-stop watcher
    def _estop_watch(self):
        """The stop channel's receiving end (this process's priority, SCHED_FIFO where allowed):
        wakes on the shared event, latches the tracker's e-stop (state first, then the arm's stop
        command; lock-free for the state, also while the loop is busy in an arm call) and publishes
        the acknowledgement at once, with the request number the engine wrote."""
        while not self._quit.is_set():
            if self.estop_ev.wait(0.2):
                self.estop_ev.clear()  # a request after this point sets it again: none is lost
                got = self.stop_slot.read() if self.stop_slot is not None else None
                self.tracker.estop("operator e-stop")
                self._acknowledge(int(got[1][0]) if got is not None else self._ack[0])

    def _acknowledge(self, request: int) -> None:
        """The stop request ``request`` is latched: publish it (with the time) at once."""
        now = self.clock()
        with self._pub_lock:
            if request >= self._ack[0]:
                self._ack = (int(request), now)
                self._still_t = float("nan")
        self._publish(now)

    def _note_still(self, now) -> None:
        """After an acknowledged stop: the first cycle in which the arm stands still."""
        if self._ack[0] <= 0 or self._still_t == self._still_t or self.tracker.state.value != "estopped":
            return
        snap = self.tracker.snapshot()
        dq = self.sim_arm.true_dq if self.sim_arm is not None else (snap.dq if snap is not None else None)
        if dq is not None and np.all(np.isfinite(dq)) and float(np.max(np.abs(dq))) < STILL_RAD_S:
            with self._pub_lock:
                self._still_t = float(now)

    # ------------------------------------------------------------------ inputs per cycle
    def _apply_target(self, now):
        """The newest target the engine wrote into the slot, once (control cycle; command thread
        before a start)."""
        with self._target_lock:  # in slot order: a late older write must never follow a newer one
            got = self.target_slot.read()
            if got is None or got[0] == self._seen_target:
                return
            self._seen_target, v = got
            head = int(v[18])
            if head in (1, 2):
                self.tracker.set_head_sphere(v[19:22], float(v[22]), frame="target" if head == 1 else "base")
            self.tracker.set_target(v[:16].reshape(4, 4), float(v[16]), bool(v[17] > 0.5), now=now)

    def _check_engine(self, now) -> bool:
        """False when the engine process is gone."""
        if self._parent_gone.is_set() or os.getppid() != self.parent_pid:
            return False
        beat = self.heart_slot.read()
        timeout = float(self.opts.get("heartbeat_timeout_s", 2.0))
        if beat is not None and now - float(beat[1][0]) > timeout:
            if not self._heart_lost:
                self._heart_lost = True
                self.tracker.estop(f"engine process not responding (no heartbeat for {now - float(beat[1][0]):.1f} s)")
        else:
            self._heart_lost = False
        return True

    # ------------------------------------------------------------------ state out
    def _publish(self, now):
        """Write the state slot (loop, command and e-stop threads; one at a time, so a newer
        state is never overwritten by an older one)."""
        with self._pub_lock:
            snap = self.tracker.snapshot()
            if snap is None:
                return
            v = np.full(STATE_N, np.nan)

            def put(name, val):
                i, n = _OFF[name]
                v[i:i + n] = np.asarray(val, dtype=float).reshape(-1)

            put("t", snap.t)
            put("state", STATES.index(self.tracker.state.value))  # the live state, not the step's
            put("connected", snap.connected)
            put("q", snap.q); put("dq", snap.dq); put("dq_cmd", snap.dq_cmd)
            put("T_tip", snap.T_base_tip_mm)
            put("has_target", snap.T_base_target_mm is not None)
            if snap.T_base_target_mm is not None:
                put("T_target", snap.T_base_target_mm)
            put("tip_error_mm", snap.tip_error_mm); put("angle_error_deg", snap.angle_error_deg)
            put("target_age_s", snap.target_age_s); put("sigma_min", snap.sigma_min)
            put("step_cost_ms", snap.step_cost_ms); put("overruns", self.tracker.overruns)
            put("keepout", snap.keepout_active)
            put("program_fault", PROGRAM_FAULTS.index(snap.program_fault) if snap.program_fault in PROGRAM_FAULTS else 7)
            put("target_stamp", self.tracker.safety.target_stamp)
            put("worst_cycle_ms", self.tracker.worst_cycle_ms)
            if self.sim_arm is not None:
                put("true_q", self.sim_arm.true_q); put("true_dq", self.sim_arm.true_dq)
            put("cycles", self.cycles); put("t_published", now)
            put("stopping", 0.0)
            put("estop_ack", self._ack[0]); put("estop_ack_t", self._ack[1]); put("still_t", self._still_t)
            self.state_slot.write(v)

    # ------------------------------------------------------------------ main loop
    def run(self):
        self.priority = elevate_priority(int(self.opts.get("fifo_priority", 10)),
                                         int(self.opts.get("fallback_nice", -10))) if self.opts.get("elevate", True) \
            else "normal priority (not requested)"
        res = self.tracker.connect()
        self.tracker.step(self.clock())
        self._publish(self.clock())
        threads = [threading.Thread(target=f, name=n, daemon=True) for f, n in
                   ((self._sender, "control-sender"), (self._commands, "control-commands"),
                    (self._estop_watch, "control-estop"))]
        for t in threads:
            t.start()
        self.outbox.put(("ready", bool(res.ok), res.reason, os.getpid(), self.priority))
        gc.collect()
        gc.freeze()  # long-lived setup objects out of the collector's way (fewer, shorter pauses)
        try:
            self._loop()
        finally:
            self._finish()

    def _loop(self):
        run_paced(self.tracker, lambda: not self._quit.is_set(), self._cycle)

    def _cycle(self, t_start) -> bool:
        """One control cycle (paced by :func:`run_paced`); False: the engine is gone, stop."""
        tr = self.tracker
        if not self._check_engine(t_start):
            self.exit_reason = "engine process gone"
            tr.estop("engine process gone: control process stops the arm and exits")
            return False
        try:
            self._apply_target(t_start)
            tr.step(t_start)
            self._note_still(t_start)
        except Exception as exc:  # step() catches loop errors; last guard
            log.exception("control process error")
            tr.estop(f"internal error in control process: {type(exc).__name__}: {exc}")
        self.cycles += 1
        self._publish(self.clock())
        return True

    def _finish(self):
        """Stop the arm until it stands still (bounded), disconnect, report, exit."""
        tr = self.tracker
        t_end = self.clock() + float(self.opts.get("exit_stop_s", 2.0))
        while self.clock() < t_end:
            t0 = self.clock()
            tr.step(t0)
            self._publish(self.clock())
            snap = tr.snapshot()
            dq = self.sim_arm.true_dq if self.sim_arm is not None else snap.dq
            if not np.all(np.isfinite(dq)) or np.max(np.abs(dq)) < 1e-4 or not snap.connected:
                break
            time.sleep(max(0.0, self.period - (self.clock() - t0)))
        snap = tr.snapshot()
        true_dq = self.sim_arm.true_dq if self.sim_arm is not None else snap.dq
        try:
            tr.disconnect()
        except Exception:
            log.exception("arm disconnect failed")
        report = {"reason": self.exit_reason, "state": tr.state.value,
                  "last_transition": tr.safety.history[-1].reason if tr.safety.history else "",
                  "max_abs_dq_rad_s": float(np.max(np.abs(true_dq))) if np.all(np.isfinite(true_dq)) else None,
                  "cycles": self.cycles, "overruns": tr.overruns, "pid": os.getpid(), "priority": self.priority}
        path = self.opts.get("exit_report")
        if path:
            try:
                with open(path, "w") as fh:
                    json.dump(report, fh)
            except OSError:
                log.exception("could not write the exit report")
        self._quit.set()
        self.outbox.put(("exit", report))
        self.outbox.put(None)


def _child_main(arm_factory, tracker_kwargs, conn, target_slot, state_slot, heart_slot, estop_ev, parent_pid, opts,
                stop_slot=None):
    logging.basicConfig(level=logging.WARNING, format="control-process %(levelname)s %(name)s: %(message)s")
    child = _Child(arm_factory, tracker_kwargs, conn, target_slot, state_slot, heart_slot, estop_ev, parent_pid, opts,
                   stop_slot)
    child.run()
    time.sleep(0.05)  # let the sender flush the exit report
