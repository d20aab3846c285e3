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
* **e-stop** (the stop channel) through shared memory and a shared ``multiprocessing.Event``:
  :meth:`ControlProcess.signal_estop` writes a request number into the stop slot and sets the
  event (no pipe, no lock the control process holds, microseconds: callable from a web server's
  event loop); a watcher thread in the child, at the child's priority, wakes on it, latches the
  tracker's e-stop (lock-free, also while the loop is busy in an arm call), commands the arm to
  stop and publishes the request number as its acknowledgement in the state slot at once.
  :meth:`ControlProcess.estop` waits for that acknowledgement (the state the engine and the page
  show is the child's, never the engine's wish); if it does not come, the command pipe is tried
  as a second route and the answer says the stop is unconfirmed;
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

import logging
import multiprocessing as mp
import os
import threading
import time
from itertools import count
from typing import Callable

import numpy as np

# the slot layout and the child side live in their own modules; re-exported (their old home)
from monotracker.robot.control_child import _child_main, _Child, elevate_priority  # noqa: F401
from monotracker.robot.control_layout import (_OFF, HEART_N, PROGRAM_FAULTS, STATE_FIELDS, STATE_N,  # noqa: F401
                                              STATES, STOP_N, TARGET_N, ControlState, _decode_state, _offsets)
from monotracker.robot.shm_channel import SeqlockSlot

log = logging.getLogger(__name__)

#: the control process runs its linear algebra in its own threads: a BLAS worker pool, created when
#: numpy is imported (before the process turns real-time), would stay at normal priority, and a
#: control cycle waiting on it would wait behind the load beside the app (priority inversion)
CHILD_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
_env_lock = threading.Lock()


def _start_with_env(proc, env: dict) -> None:
    """Start ``proc`` (spawn: a new interpreter inheriting ``os.environ``) with ``env`` set."""
    with _env_lock:
        saved = {k: os.environ.get(k) for k in env}
        os.environ.update(env)
        try:
            proc.start()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v


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
    ``exit_stop_s`` (2.0), ``elevate`` (True), ``fifo_priority`` (10), ``fallback_nice`` (-10),
    ``exit_report`` (path).
    Raises :class:`ControlProcessError` (one line) if the child does not come up within
    ``start_timeout_s``."""

    COMMAND_TIMEOUT_S = 10.0
    #: how long :meth:`estop` waits for the control process's acknowledgement before it tries the
    #: command pipe as well (s)
    ESTOP_ACK_TIMEOUT_S = 1.0

    def __init__(self, arm_factory: Callable, tracker_kwargs: dict | None = None,
                 on_event: Callable[[str, object], None] | None = None, opts: dict | None = None,
                 start_timeout_s: float = 120.0):
        ctx = mp.get_context("spawn")
        self.on_event = on_event
        self.opts = dict(opts or {})
        self.target_slot = SeqlockSlot(TARGET_N)
        self.state_slot = SeqlockSlot(STATE_N)
        self.heart_slot = SeqlockSlot(HEART_N)
        self.stop_slot = SeqlockSlot(STOP_N)
        self._stop_lock = threading.Lock()  # one writer of the stop slot at a time (two tabs may press STOP)
        self._stop_n = 0
        self.estop_ev = ctx.Event()
        self._conn, child_conn = ctx.Pipe(duplex=True)
        self._send_lock = threading.Lock()
        self._ids = count(1)
        self._pending: dict[int, list] = {}
        self._pending_lock = threading.Lock()
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
                                      self.state_slot, self.heart_slot, self.estop_ev, os.getpid(), self.opts,
                                      self.stop_slot),
                                daemon=True)
        _start_with_env(self.proc, CHILD_ENV)
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
            except Exception:
                # close() from another thread while recv() waited leaves the connection without a
                # handle (CPython then raises TypeError inside recv); anything else is logged.
                # Either way the reader ends and every waiting command is answered "not running"
                if not self._conn.closed:
                    log.exception("robot control reader failed")
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
                    except Exception:
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

    def signal_estop(self) -> int:
        """The stop channel: write the next request number into the stop slot and set the shared
        event the control process's e-stop watcher waits on; returns the request number. Never
        blocks on the control process (a lock held only here, for two floats), never raises:
        safe on a web server's event loop. The child's acknowledgement is ``state().estop_ack``."""
        with self._stop_lock:
            self._stop_n += 1
            n = self._stop_n
            self.stop_slot.write([float(n), time.monotonic()])
        self.estop_ev.set()
        return n

    def estop(self, reason: str = "operator e-stop", timeout_s: float | None = None):
        """Signal the stop (:meth:`signal_estop`) and wait (up to ``timeout_s``, default
        :data:`ESTOP_ACK_TIMEOUT_S`) until the control process acknowledges it; without an
        acknowledgement the command pipe is tried too. Returns ``(confirmed, one line)``."""
        t0 = time.monotonic()
        n = self.signal_estop()
        limit = self.ESTOP_ACK_TIMEOUT_S if timeout_s is None else float(timeout_s)
        while True:
            st = self.state()
            if st is not None and st.estop_ack >= n:
                return True, f"e-stopped (the control process confirmed in {1000 * (time.monotonic() - t0):.0f} ms)"
            if not self.alive or time.monotonic() - t0 > limit:
                break
            time.sleep(0.001)
        ok, why = self.command("estop", reason, n, timeout=2.0)
        if ok:
            return True, ("e-stopped (confirmed over the command pipe; the stop channel did not answer within "
                          f"{1000 * limit:.0f} ms)")
        return False, (f"STOP signalled but the robot control process has not confirmed it ({why}): "
                       "use the robot's own emergency stop")

    def reset(self):
        return self.command("reset")

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
        """The state as the engine should show it: the control process's own (its published
        state; a stop shows once the child has latched it), ``estopped`` when the child is gone."""
        if not self.alive:
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
