"""The robot's control loop in its own process, out of reach of vision, UI and logging.

The engine process (camera, registration, web server) shares one GIL and one scheduler queue;
a control thread inside it overran its 8 ms period up to 1.67 s on a loaded machine. Here the
:class:`~monotracker.robot.tracker.Tracker` (APFF controller + safety layer + arm backend) runs
in a ``spawn``-ed child process, at SCHED_FIFO priority where the OS allows (else a lower nice
value, else normal; :attr:`ControlProcess.priority` says which and why), with:

* **targets** in through a shared-memory seqlock slot (:class:`~monotracker.robot.shm_channel.SeqlockSlot`):
  ``[T_base_target (16, mm), capture stamp (s), valid, head sphere (frame, centre mm, radius mm)]``;
  the child applies a target when its sequence number changes, once per control cycle;
* **state** back through a second seqlock slot (joint state, tip pose, state machine, errors,
  program fault, cycle counters; see :data:`STATE_FIELDS`), published every cycle;
* **commands** (arm, disarm, start/stop tracking, reset, connect, head sphere, drop) over a pipe,
  executed in the child by a command thread under the tracker's lock, answered with
  ``(ok, reason)``; events (transitions, warnings) come back the same way, sent by a sender thread
  so that a stalled engine can never block the control loop on a full pipe;
* **e-stop** through a shared ``multiprocessing.Event``: a watcher thread in the child wakes on
  it and latches the tracker's e-stop at once (lock-free, also while the loop is busy in an arm
  call); the engine side latches its own view too, so the UI shows ``estopped`` immediately;
* **engine gone**: the child checks every cycle that its parent is alive (``os.getppid``) and
  that the engine's heartbeat (a parent thread, 20 Hz) is fresh. Parent dead: e-stop, stop
  the arm until it stands still (at most ``exit_stop_s``), disconnect, exit. Heartbeat older than
  ``heartbeat_timeout_s`` (parent hung or stopped): e-stop (latched; the operator resets). Targets
  no longer fed: the safety layer's stale-target hold, as in-process.

Clock: the child's clock is ``time.monotonic`` (system-wide), the engine's real session clock,
so capture stamps mean the same on both sides. For ``clock="sim"`` sessions use the in-process
:class:`Tracker` (deterministic stepping); this class is for real time.

Period timing: the child records the start time of every cycle; :meth:`ControlProcess.cycle_starts`
returns them (``benchmarks/control_jitter.py``).
"""

from __future__ import annotations

import gc
import json
import logging
import multiprocessing as mp
import os
import queue
import threading
import time
from dataclasses import dataclass
from itertools import count
from typing import Callable

import numpy as np

from monotracker.robot.shm_channel import SeqlockSlot

log = logging.getLogger(__name__)

STATES = ("disarmed", "armed", "tracking", "holding", "estopped")
PROGRAM_FAULTS = ("", "watchdog", "pendant", "paused", "protective_stop", "emergency_stop",
                  "safeguard_stop", "not_running")

#: target slot: T (16, mm), stamp, valid, head_set (0 none, 1 target frame, 2 base frame), centre (3, mm), radius (mm)
TARGET_N = 16 + 2 + 1 + 3 + 1
#: the engine's heartbeat slot: [monotonic time of the last beat]
HEART_N = 1
#: state slot fields (name, size), in order
STATE_FIELDS = (
    ("t", 1), ("state", 1), ("connected", 1), ("q", 6), ("dq", 6), ("dq_cmd", 6), ("T_tip", 16),
    ("has_target", 1), ("T_target", 16), ("tip_error_mm", 1), ("angle_error_deg", 1),
    ("target_age_s", 1), ("sigma_min", 1), ("step_cost_ms", 1), ("overruns", 1), ("keepout", 1),
    ("program_fault", 1), ("target_stamp", 1), ("worst_cycle_ms", 1), ("true_q", 6), ("true_dq", 6),
    ("cycles", 1), ("t_published", 1), ("stopping", 1),
)
STATE_N = sum(n for _, n in STATE_FIELDS)


def _offsets():
    out, i = {}, 0
    for name, n in STATE_FIELDS:
        out[name] = (i, n)
        i += n
    return out


_OFF = _offsets()


@dataclass(frozen=True)
class ControlState:
    """One consistent state published by the control process (see :data:`STATE_FIELDS`).
    Poses mm (base frame); ``q`` rad, ``dq`` rad/s; ``true_q``/``true_dq`` the simulated arm's
    truth (NaN for a real arm); ``t`` the child's clock (s) at the cycle; ``state`` one of
    :data:`STATES`; ``program_fault`` one of :data:`PROGRAM_FAULTS`."""

    t: float
    state: str
    connected: bool
    q: np.ndarray
    dq: np.ndarray
    dq_cmd: np.ndarray
    T_base_tip_mm: np.ndarray
    T_base_target_mm: np.ndarray | None
    tip_error_mm: float
    angle_error_deg: float
    target_age_s: float
    sigma_min: float
    step_cost_ms: float
    overruns: int
    keepout_active: bool
    program_fault: str
    target_stamp: float
    worst_cycle_ms: float
    true_q: np.ndarray
    true_dq: np.ndarray
    cycles: int
    t_published: float


def _decode_state(v: np.ndarray) -> ControlState:
    def g(name):
        i, n = _OFF[name]
        return v[i] if n == 1 else v[i:i + n].copy()

    has_t = g("has_target") > 0.5
    return ControlState(
        t=float(g("t")), state=STATES[int(g("state"))], connected=bool(g("connected") > 0.5),
        q=g("q"), dq=g("dq"), dq_cmd=g("dq_cmd"), T_base_tip_mm=g("T_tip").reshape(4, 4),
        T_base_target_mm=g("T_target").reshape(4, 4) if has_t else None,
        tip_error_mm=float(g("tip_error_mm")), angle_error_deg=float(g("angle_error_deg")),
        target_age_s=float(g("target_age_s")), sigma_min=float(g("sigma_min")),
        step_cost_ms=float(g("step_cost_ms")), overruns=int(g("overruns")), keepout_active=bool(g("keepout") > 0.5),
        program_fault=PROGRAM_FAULTS[int(g("program_fault"))], target_stamp=float(g("target_stamp")),
        worst_cycle_ms=float(g("worst_cycle_ms")), true_q=g("true_q"), true_dq=g("true_dq"),
        cycles=int(g("cycles")), t_published=float(g("t_published")),
    )


# ====================================================================== child side
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
                 parent_pid, opts):
        from monotracker.robot.tracker import Tracker

        self.conn = conn
        self.target_slot, self.state_slot, self.heart_slot = target_slot, state_slot, heart_slot
        self.estop_ev = estop_ev
        self.parent_pid = parent_pid
        self.opts = opts
        self.clock = time.monotonic
        self.outbox: queue.SimpleQueue = queue.SimpleQueue()
        arm = arm_factory()
        self.sim_arm = arm if hasattr(arm, "true_q") else None
        self.tracker = Tracker(arm, clock=self.clock, on_event=self._on_event, **tracker_kwargs)
        self.period = self.tracker.period
        self._seen_target = 0.0
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
                       "t": payload.t}
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
                elif name == "estop":
                    res = tr.estop(*args)
                elif name in ("arm", "disarm", "start_tracking", "stop_tracking", "reset", "connect"):
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
            except Exception as exc:  # noqa: BLE001 - a command never kills the control process
                log.exception("control command %s failed", name)
                ok, reason = False, f"{name} failed: {type(exc).__name__}: {exc}"
            self._publish(self.clock())  # the reply's effect is visible once the reply arrives
            self.outbox.put(("reply", cid, bool(ok), reason))

    # ------------------------------------------------------------------ e-stop watcher
    def _estop_watch(self):
        while not self._quit.is_set():
            if self.estop_ev.wait(0.2):
                self.tracker.estop("operator e-stop")
                self.estop_ev.clear()

    # ------------------------------------------------------------------ inputs per cycle
    def _apply_target(self, now):
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
        with self._pub_lock:
            self.state_slot.write(v)

    # ------------------------------------------------------------------ main loop
    def run(self):
        self._pub_lock = threading.Lock()
        self.priority = elevate_priority(int(self.opts.get("fifo_priority", 10))) if self.opts.get("elevate", True) \
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
        tr = self.tracker
        nxt = self.clock()
        while not self._quit.is_set():
            t_start = self.clock()
            self.starts.append(t_start)
            token = tr._begin_cycle()
            if not self._check_engine(t_start):
                self.exit_reason = "engine process gone"
                tr.estop("engine process gone: control process stops the arm and exits")
                return
            try:
                self._apply_target(t_start)
                tr.step(t_start)
            except Exception as exc:  # noqa: BLE001 - step() catches loop errors; last guard
                log.exception("control process error")
                tr.estop(f"internal error in control process: {type(exc).__name__}: {exc}")
            self.cycles += 1
            self._publish(self.clock())
            nxt += self.period
            t_end = self.clock()
            tr.worst_cycle_ms = max(tr.worst_cycle_ms, (t_end - t_start) * 1e3)
            delay = nxt - t_end
            if delay < 0:
                tr._report_overrun(-delay)
            if delay < -self.period:
                nxt = self.clock()
            elif delay > 0 and not tr._wait_cycle(token):
                time.sleep(delay)

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
        except Exception:  # noqa: BLE001
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


def _child_main(arm_factory, tracker_kwargs, conn, target_slot, state_slot, heart_slot, estop_ev, parent_pid, opts):
    logging.basicConfig(level=logging.WARNING, format="control-process %(levelname)s %(name)s: %(message)s")
    child = _Child(arm_factory, tracker_kwargs, conn, target_slot, state_slot, heart_slot, estop_ev, parent_pid, opts)
    child.run()
    time.sleep(0.05)  # let the sender flush the exit report


# ====================================================================== engine side
class ControlProcessError(RuntimeError):
    pass


class ControlProcess:
    """Engine-side handle of the control process, with the :class:`Tracker`'s operator API.

    ``arm_factory``: picklable callable returning the arm backend in the child (e.g.
    ``functools.partial(SimulatedArm, q0=q0, period_s=1/125)``). ``tracker_kwargs``: passed to
    :class:`Tracker` (``variant``, ``rate_hz``, ``predict_target``, ...; not ``clock``/``arm``).
    ``on_event(kind, payload)``: ``"transition"`` (dict from/to/reason/t) and ``"warning"`` (str),
    called on the handle's reader thread. ``opts``: ``heartbeat_timeout_s`` (2.0),
    ``exit_stop_s`` (2.0), ``elevate`` (True), ``fifo_priority`` (10), ``exit_report`` (path).
    Raises :class:`ControlProcessError` (one line) if the child does not come up within
    ``start_timeout_s``."""

    COMMAND_TIMEOUT_S = 10.0

    def __init__(self, arm_factory: Callable, tracker_kwargs: dict | None = None,
                 on_event: Callable[[str, object], None] | None = None, opts: dict | None = None,
                 start_timeout_s: float = 120.0):
        ctx = mp.get_context("spawn")
        self.on_event = on_event
        self.opts = dict(opts or {})
        self.target_slot = SeqlockSlot(TARGET_N)
        self.state_slot = SeqlockSlot(STATE_N)
        self.heart_slot = SeqlockSlot(HEART_N)
        self.estop_ev = ctx.Event()
        self._conn, child_conn = ctx.Pipe(duplex=True)
        self._send_lock = threading.Lock()
        self._ids = count(1)
        self._pending: dict[int, list] = {}
        self._pending_lock = threading.Lock()
        self._estop_latched = False
        self._head = (0, np.zeros(3), 0.0)
        self.last_reason = ""
        self.program_fault_reason = ""
        self.exit_report: dict | None = None
        self._ready = threading.Event()
        self._ready_msg = None
        self._alive = True
        self._beat = threading.Event()
        self.heart_slot.write([time.monotonic()])
        self.proc = ctx.Process(target=_child_main, name="monotracker-control",
                                args=(arm_factory, dict(tracker_kwargs or {}), child_conn, self.target_slot,
                                      self.state_slot, self.heart_slot, self.estop_ev, os.getpid(), self.opts),
                                daemon=True)
        self.proc.start()
        child_conn.close()
        self._reader = threading.Thread(target=self._read_loop, name="monotracker-control-reader", daemon=True)
        self._reader.start()
        self._heart = threading.Thread(target=self._heartbeat, name="monotracker-control-heartbeat", daemon=True)
        self._heart.start()
        deadline = time.monotonic() + start_timeout_s
        while not self._ready.wait(0.1):
            if not self.proc.is_alive() or time.monotonic() > deadline:
                self.close()
                raise ControlProcessError("the robot control process did not start"
                                          + ("" if self.proc.exitcode is None else f" (exit code {self.proc.exitcode})"))
        _, ok, reason, self.pid, self.priority = self._ready_msg
        self.connect_result = (ok, reason)

    # ------------------------------------------------------------------ threads
    def _heartbeat(self):
        while self._alive and not self._beat.wait(0.05):
            self.heart_slot.write([time.monotonic()])

    def stop_heartbeat(self) -> None:
        """Stop beating (tests: an engine that hangs)."""
        self._beat.set()

    def _read_loop(self):
        while True:
            try:
                msg = self._conn.recv()
            except (EOFError, OSError):
                break
            kind = msg[0]
            if kind == "reply":
                with self._pending_lock:
                    slot = self._pending.pop(msg[1], None)
                if slot is not None:
                    slot[1] = (msg[2], msg[3])
                    slot[0].set()
            elif kind == "event":
                if msg[1] == "transition":
                    self.last_reason = msg[2]["reason"]
                if self.on_event is not None:
                    try:
                        self.on_event(msg[1], msg[2])
                    except Exception:  # noqa: BLE001
                        log.exception("control event callback failed")
            elif kind == "ready":
                self._ready_msg = msg
                self._ready.set()
            elif kind == "exit":
                self.exit_report = msg[1]
        self._alive = False
        with self._pending_lock:
            for slot in self._pending.values():
                slot[1] = (False, "the robot control process is not running")
                slot[0].set()
            self._pending.clear()

    # ------------------------------------------------------------------ commands
    @property
    def alive(self) -> bool:
        return self._alive and self.proc.is_alive()

    def command(self, name: str, *args, timeout: float | None = None):
        """Send a command; returns ``(ok, reason)`` (``reason`` may be data for queries)."""
        if not self.alive:
            return False, "the robot control process is not running"
        cid = next(self._ids)
        slot = [threading.Event(), None]
        with self._pending_lock:
            self._pending[cid] = slot
        try:
            with self._send_lock:
                self._conn.send((cid, name, args))
        except (OSError, ValueError, BrokenPipeError) as exc:
            with self._pending_lock:
                self._pending.pop(cid, None)
            return False, f"the robot control process is not reachable ({exc})"
        if not slot[0].wait(self.COMMAND_TIMEOUT_S if timeout is None else timeout):
            with self._pending_lock:
                self._pending.pop(cid, None)
            return False, f"the robot control process did not answer {name!r} in time"
        return slot[1]

    def estop(self, reason: str = "operator e-stop"):
        """Latched at once on both sides: the shared event wakes the child's e-stop watcher
        (milliseconds, also while its loop is busy); then confirmed over the pipe."""
        self._estop_latched = True
        self.estop_ev.set()
        ok, why = self.command("estop", reason, timeout=2.0)
        if not ok:
            return True, f"e-stop signalled ({why})"
        return True, "e-stopped"

    def reset(self):
        ok, reason = self.command("reset")
        if ok:
            self._estop_latched = False
        return ok, reason

    def set_head_sphere(self, centre_mm, radius_mm: float, frame: str = "target"):
        c = np.asarray(centre_mm, dtype=float).reshape(-1)
        if c.shape != (3,) or not np.all(np.isfinite(c)) or not (np.isfinite(radius_mm) and radius_mm > 0):
            return False, "head sphere needs a finite centre (3 values, mm) and radius > 0 mm"
        if frame not in ("target", "base"):
            return False, f"head sphere frame must be 'target' or 'base', not {frame!r}"
        self._head = (1 if frame == "target" else 2, c, float(radius_mm))
        return True, "head sphere set (sent with the next target)"

    def set_target(self, T_base_target_mm, stamp: float, valid: bool = True) -> None:
        """Write the target slot (never blocks on the child)."""
        try:
            T = np.asarray(T_base_target_mm, dtype=float).reshape(4, 4)
        except (ValueError, TypeError):
            T = np.full((4, 4), np.nan)
        try:
            stamp = float(stamp)
        except (TypeError, ValueError):
            stamp = float("nan")
        code, c, r = self._head
        self.target_slot.write(np.concatenate([T.reshape(-1), [stamp, 1.0 if valid else 0.0, code], c, [r]]))

    def state(self) -> ControlState | None:
        got = self.state_slot.read()
        return None if got is None else _decode_state(got[1])

    def live_state(self) -> str:
        """The state as the engine should show it: ``estopped`` at once after :meth:`estop`,
        or when the child is gone."""
        if self._estop_latched or not self.alive:
            return "estopped"
        st = self.state()
        return "disarmed" if st is None else st.state

    def cycle_starts(self) -> np.ndarray:
        ok, data = self.command("cycle_starts", timeout=30.0)
        return data if ok else np.zeros(0)

    def close(self, timeout_s: float = 10.0) -> None:
        """Ask the child to stop the arm and exit; kill it if it does not (never raises)."""
        try:
            if self.alive:
                self.command("shutdown", timeout=timeout_s)
            self.proc.join(timeout_s)
            if self.proc.is_alive():
                log.error("robot control process did not exit; terminating it")
                self.proc.terminate()
                self.proc.join(5.0)
            if self.proc.is_alive():
                self.proc.kill()
                self.proc.join(5.0)
        finally:
            self._alive = False
            self._beat.set()
            try:
                self._conn.close()
            except OSError:
                pass
            self._reader.join(2.0)
            self._heart.join(2.0)
