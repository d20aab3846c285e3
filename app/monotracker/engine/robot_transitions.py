"""The robot's state transitions in the order the control loop made them, for the audit log.

The safety layer numbers every transition (``robot.safety.Transition.seq``) under its lock, but
reports it to listeners outside that lock, from whichever thread made it (the control loop, the
e-stop watcher, a command), and from the control process through a pipe: two transitions made
a moment apart by two threads may be reported in swapped order, and a state polled from the
control process's shared memory runs ahead of the report that explains it. The engine used to
write its ``robot_state`` audit rows from the polled state with the newest *reported* reason,
so a row could carry the previous transition's reason (issue 34).

:class:`TransitionLog` takes the reports as they come and hands them back strictly in sequence
order, each with its own reason; the engine writes one ``robot_state`` row per transition from
it (``engine/loop/robot.py``). Changes the engine itself decides (the control process is gone)
are added with :meth:`TransitionLog.add_local`, after every report already numbered.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class RobotTransition:
    """One robot state change: ``from_state`` -> ``to_state`` because ``reason``; ``t`` the
    control loop's clock (s) when it happened (None for one the engine decided); ``seq`` the
    safety layer's number (None for the engine's own)."""

    from_state: str
    to_state: str
    reason: str
    t: float | None = None
    seq: int | None = None


class TransitionLog:
    """Reports in, transitions out in ``seq`` order (thread-safe).

    ``gap_timeout_s`` (2 s): a missing number (a report that never came) holds the later ones
    back at most this long; then they are released and the gap is said in their reason."""

    def __init__(self, gap_timeout_s: float = 2.0, clock=time.monotonic, first_state: str = "disarmed"):
        self.gap_timeout_s = float(gap_timeout_s)
        self.clock = clock
        self._lock = threading.Lock()
        self._next = 1
        self._pending: dict[int, tuple[RobotTransition, float]] = {}
        self._ready: list[RobotTransition] = []
        self._last_to = str(first_state)  # where the newest transition handed on went

    def add(self, from_state: str, to_state: str, reason: str, t: float | None, seq: int | None) -> None:
        """A transition the control loop reported (``seq`` from its safety layer; None: unnumbered,
        taken as the next in order)."""
        tr = RobotTransition(str(from_state), str(to_state), str(reason), None if t is None else float(t),
                             None if seq is None else int(seq))
        with self._lock:
            if tr.seq is None:
                self._append_locked(tr)
                return
            if tr.seq < self._next:
                return  # a duplicate of one already handed on
            self._pending[tr.seq] = (tr, self.clock())
            self._release_locked()

    def add_local(self, to_state: str, reason: str) -> None:
        """A change the engine decided itself (no control-loop report explains it), from the
        state the newest transition went to: after every numbered report that came in (a gap,
        if any, is given up). Nothing when the robot is already in ``to_state``."""
        with self._lock:
            self._flush_locked(force=True)
            if self._last_to != str(to_state):
                self._append_locked(RobotTransition(self._last_to, str(to_state), str(reason)))

    def _append_locked(self, tr: RobotTransition) -> None:
        self._ready.append(tr)
        self._last_to = tr.to_state

    def drain(self) -> list[RobotTransition]:
        """The transitions ready (in order) since the last call."""
        with self._lock:
            self._flush_locked(force=False)
            out, self._ready = self._ready, []
            return out

    def _release_locked(self) -> None:
        while self._next in self._pending:
            self._append_locked(self._pending.pop(self._next)[0])
            self._next += 1

    def _flush_locked(self, force: bool) -> None:
        self._release_locked()
        if not self._pending:
            return
        oldest = min(arrived for _, arrived in self._pending.values())
        if not force and self.clock() - oldest < self.gap_timeout_s:
            return
        first = min(self._pending)
        missing = first - self._next
        self._next = first
        tr = self._pending[first][0]
        self._pending[first] = (RobotTransition(tr.from_state, tr.to_state, tr.reason + f" [{missing} earlier "
                                                f"transition report(s) lost]", tr.t, tr.seq), 0.0)
        self._release_locked()
        self._flush_locked(force)
