"""Events and alerts: one bus from the engine's threads to its subscribers (the UI) and the audit log.

Every decision (fiducial confirmed, arm armed, tracking started) and every condition the loop
notices (occlusion, stale pose, camera freeze, robot fault) becomes an :class:`Event`. Events whose
``kind`` is ``"alert"`` are what the operator must see; ``"event"`` records are decisions and
state changes. All of them go to the append-only audit log (its sink only queues them: the audit
log writes on its own thread, so a stop, hold or alarm never waits on the database) and to every
subscriber.

Subscribers are called on the bus's own dispatcher thread once :meth:`EventBus.start` ran (so a
slow UI callback never delays the control loop), or synchronously on the publishing thread before
that (deterministic tests and the simulated-clock demo). A subscriber that raises is logged and
kept; it never breaks the engine.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

log = logging.getLogger(__name__)

LEVELS = ("info", "warning", "alarm")


@dataclass(frozen=True)
class Event:
    """One event or alert.

    ``t``: wall-clock time (Unix epoch s) when it was raised. ``t_session``: the session clock
    (s; the simulated clock in simulated-clock runs, ``time.monotonic()`` otherwise).
    ``kind``: ``"alert"`` (for the operator) or ``"event"`` (a decision / state change).
    ``level``: ``"info" | "warning" | "alarm"``. ``code``: a stable machine-readable name
    (e.g. ``"occlusion"``, ``"pose_stale"``, ``"camera_freeze"``, ``"robot_disconnected"``,
    ``"bad_pose"``, ``"armed"``). ``message``: one human-readable line. ``data``: JSON-ready extras.
    """

    t: float
    t_session: float
    kind: str
    level: str
    code: str
    message: str
    data: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {
            "t": self.t,
            "t_session": self.t_session,
            "kind": self.kind,
            "level": self.level,
            "code": self.code,
            "message": self.message,
            "data": dict(self.data),
        }


Subscriber = Callable[[Event], Any]


class EventBus:
    """Publish events to a ring buffer, an optional sink (the audit log) and subscribers.

    ``sink(event)`` is called inside :meth:`publish`; it must not block (the audit log's sink
    only puts the event on its queue).
    ``clock()`` gives the session time stamped on each event.
    ``alert_level(code, level)``: the level an alert with ``code`` carries (the engine passes
    :func:`~monotracker.engine.alarms.level_of`: a catalogued code's level is its row's).
    """

    def __init__(self, sink: Callable[[Event], None] | None = None, clock: Callable[[], float] = time.monotonic,
                 keep: int = 200, alert_level: Callable[[str, str], str] | None = None):
        self._sink = sink
        self._clock = clock
        self._alert_level = alert_level
        self._lock = threading.Lock()
        self._recent: deque[Event] = deque(maxlen=keep)
        # alerts kept apart so that a burst of events (wrong PIN tries, state changes) cannot
        # push the operator's alerts out of the recent list
        self._recent_alerts: deque[Event] = deque(maxlen=keep)
        self._subscribers: dict[int, Subscriber] = {}
        self._next_id = 0
        self._queue: queue.Queue[Event | None] = queue.Queue()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ subscribers
    def subscribe(self, callback: Subscriber) -> Callable[[], None]:
        """Call ``callback(event)`` for every later event; returns the unsubscribe function."""
        if not callable(callback):
            raise TypeError("subscribe needs a callable")
        with self._lock:
            sid = self._next_id
            self._next_id += 1
            self._subscribers[sid] = callback

        def unsubscribe() -> None:
            with self._lock:
                self._subscribers.pop(sid, None)

        return unsubscribe

    # ------------------------------------------------------------------ publishing
    def publish(self, kind: str, level: str, code: str, message: str, data: dict | None = None) -> Event:
        if kind == "alert" and self._alert_level is not None:
            level = self._alert_level(code, level)
        if level not in LEVELS:
            raise ValueError(f"unknown level {level!r}")
        ev = Event(t=time.time(), t_session=float(self._clock()), kind=kind, level=level, code=code,
                   message=message, data=dict(data or {}))
        with self._lock:
            self._recent.append(ev)
            if kind == "alert":
                self._recent_alerts.append(ev)
        if self._sink is not None:
            try:
                self._sink(ev)
            except Exception:  # a failing disk must not stop the control loop
                log.exception("audit sink failed for %s", code)
        if self._thread is not None:
            self._queue.put(ev)
        else:
            self._deliver(ev)
        return ev

    def alert(self, level: str, code: str, message: str, data: dict | None = None) -> Event:
        return self.publish("alert", level, code, message, data)

    def event(self, code: str, message: str, data: dict | None = None, level: str = "info") -> Event:
        return self.publish("event", level, code, message, data)

    def recent(self, kind: str | None = None) -> list[Event]:
        """Copies of the recent events (oldest first), optionally only one kind."""
        with self._lock:
            items = list(self._recent_alerts if kind == "alert" else self._recent)
        return [e for e in items if kind is None or e.kind == kind]

    def _deliver(self, ev: Event) -> None:
        with self._lock:
            subs = list(self._subscribers.values())
        for cb in subs:
            try:
                cb(ev)
            except Exception:  # a broken subscriber must not break the engine
                log.exception("event subscriber failed on %s", ev.code)

    # ------------------------------------------------------------------ dispatcher thread
    def start(self) -> None:
        """Deliver to subscribers from a dedicated thread from now on."""
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="monotracker-events", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Deliver what is queued, then stop the dispatcher (later events are delivered inline)."""
        th = self._thread
        if th is None:
            return
        self._queue.put(None)
        th.join(timeout)
        self._thread = None

    def _run(self) -> None:
        while True:
            ev = self._queue.get()
            if ev is None:
                return
            self._deliver(ev)
