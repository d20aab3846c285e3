"""Simulated UR10 joint-velocity servo (the default backend; digital twin for tests/benchmarks).

Model (per joint, 1 ms sub-steps): commanded velocities reach the joint after ``delay_s``
(communication + controller latency), the joint velocity follows them with a first-order lag
``tau_s`` and at most ``acceleration`` (the value sent with the command, like UR's speedJ), then
integrates into position. Like a real UR it stops (decelerating at ``watchdog_decel``) when no
command arrives for ``watchdog_s``. ``true_q``/``true_dq`` are the truth; ``read()`` adds
optional Gaussian noise. Time comes from ``clock`` (monotonic s); tests and benchmarks pass a
:class:`ManualClock` to run deterministically faster than real time.
"""

from __future__ import annotations

import collections
import threading
import time

import numpy as np

from monotracker.robot.arm import Arm, ArmError, ArmState
from monotracker.robot.kinematics import Q_READY


class ManualClock:
    """A clock that only moves when told to (simulated time, s)."""

    def __init__(self, t0: float = 0.0):
        self.t = float(t0)

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> float:
        self.t += float(dt)
        return self.t


class SimulatedArm(Arm):
    def __init__(self, q0: np.ndarray | None = None, clock=time.monotonic, period_s: float = 1.0 / 125.0,
                 delay_s: float = 0.008, tau_s: float = 0.012, noise_rad: float = 0.0,
                 watchdog_s: float = 0.1, watchdog_decel: float = 4.0, seed: int = 0):
        self.clock = clock
        self.period_s = period_s
        self.delay_s = delay_s
        self.tau_s = tau_s
        self.noise_rad = noise_rad
        self.watchdog_s = watchdog_s
        self.watchdog_decel = watchdog_decel
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self.true_q = np.array(Q_READY if q0 is None else q0, dtype=float)
        self.true_dq = np.zeros(6)
        self._t = None
        self._connected = False
        #: (time it takes effect, target velocity, acceleration)
        self._queue: collections.deque = collections.deque()
        self._active = (np.zeros(6), 4.0)
        self._last_cmd_t = -np.inf
        self.commands = 0
        self.stops = 0
        self.fail_next_read = False

    # -------------------------------------------------------------- interface
    def connect(self) -> None:
        with self._lock:
            self._connected = True
            self._t = self.clock()
            self._last_cmd_t = self._t

    def disconnect(self) -> None:
        with self._lock:
            self._connected = False

    def is_connected(self) -> bool:
        return self._connected

    def drop_connection(self) -> None:
        """Fault injection: the link dies; the arm itself decelerates like a real UR would."""
        with self._lock:
            self._advance(self.clock())
            self._connected = False
            self._queue.clear()
            self._queue.append((self._t, np.zeros(6), self.watchdog_decel))

    def read(self) -> ArmState:
        with self._lock:
            now = self.clock()
            self._advance(now)
            if not self._connected:
                raise ArmError("simulated arm: not connected")
            q = self.true_q + (self._rng.normal(0, self.noise_rad, 6) if self.noise_rad else 0.0)
            return ArmState(np.array(q), self.true_dq.copy(), now)

    def command_velocity(self, dq: np.ndarray, acceleration: float) -> None:
        with self._lock:
            now = self.clock()
            self._advance(now)
            if not self._connected:
                raise ArmError("simulated arm: not connected")
            dq = np.asarray(dq, dtype=float)
            if dq.shape != (6,) or not np.all(np.isfinite(dq)):
                raise ArmError("simulated arm: joint velocity command must be 6 finite numbers")
            self._queue.append((now + self.delay_s, dq.copy(), float(acceleration)))
            self._last_cmd_t = now
            self.commands += 1

    def stop(self, deceleration: float) -> None:
        with self._lock:
            now = self.clock()
            if self._t is not None:
                self._advance(now)
            self._queue.append((now + self.delay_s, np.zeros(6), float(deceleration)))
            self._last_cmd_t = now
            self.stops += 1

    # -------------------------------------------------------------- physics
    def advance_to(self, t: float) -> None:
        """Integrate the joint model up to time ``t`` (s)."""
        with self._lock:
            self._advance(t)

    def _advance(self, t: float) -> None:
        if self._t is None:
            self._t = t
            return
        h_max = 0.001
        while self._t < t - 1e-12:
            h = min(h_max, t - self._t)
            while self._queue and self._queue[0][0] <= self._t + 1e-12:
                _, v, a = self._queue.popleft()
                self._active = (v, a)
            target, acc = self._active
            if self._t - self._last_cmd_t > self.watchdog_s and np.any(target != 0):
                self._active = (np.zeros(6), self.watchdog_decel)
                target, acc = self._active
            alpha = 1.0 - np.exp(-h / self.tau_s)
            dv = np.clip((target - self.true_dq) * alpha, -acc * h, acc * h)
            self.true_dq = self.true_dq + dv
            self.true_q = self.true_q + self.true_dq * h
            self._t += h
