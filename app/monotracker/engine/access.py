"""Who may drive the session: the PIN guard, the control arbiter, per-client proxies, and
:class:`Access`, the session's part that holds them.

Small pieces, no threads of their own, no UI knowledge (the web app consumes them):

* :class:`PinGuard` checks the operator PIN for arming *and* for taking control. Wrong tries are
  counted; after ``max_tries`` consecutive wrong tries the PIN is locked for ``lockout_s``
  (30 s), and each further lockout in a row doubles that time (60 s, 120 s, ...). While locked
  even the right PIN is refused. A right PIN (outside a lockout) clears the count and the
  doubling. The PIN itself is never part of a message or a log line.
* :class:`ControlArbiter` remembers which browser client is in control (one at a time, or nobody).
* :class:`ClientSession` is what one browser client drives: every read is forwarded to the
  :class:`~monotracker.engine.session.Session` as is, every command that changes the session is
  refused unless that client is the one in control, and :meth:`ClientSession.estop` always works.
  It is typed on :class:`GuardedSession`, the little it needs of the session.
* :class:`Access` is the session's part over them: PIN tries (audit rows, the ``pin_lockout``
  alarm), taking and releasing control, the web login's lockout alarm.

Calling the :class:`~monotracker.engine.session.Session` directly (headless demo, library users,
tests) is the local operator: unrestricted.

Times are session-clock seconds (``Session.clock()``: the simulated clock in ``clock="sim"``
sessions, ``time.monotonic()`` otherwise).
"""

from __future__ import annotations

import hmac
import math
import threading
from typing import Protocol

from monotracker.engine.snapshot import CommandResult, ControlSummary

NOT_IN_CONTROL = "another station is in control: take control with the PIN"


class PinGuard:
    """The operator PIN with a wrong-try limit (shared by arming and taking control).

    ``pin``: the PIN to accept (compared in constant time). ``max_tries`` (5): consecutive wrong
    tries that start a lockout. ``lockout_s`` (30 s): the first lockout; each lockout that follows
    another without a right PIN in between lasts twice as long, up to ``max_lockout_s``.
    ``noun``: what the secret is called in the refusals ("PIN"; the web login uses "password").
    """

    def __init__(self, pin: str, max_tries: int = 5, lockout_s: float = 30.0, max_lockout_s: float = 3600.0,
                 noun: str = "PIN"):
        if not str(pin):
            raise ValueError("the PIN must not be empty")
        self._pin = str(pin).encode()
        self.max_tries = max(1, int(max_tries))
        self.lockout_s = float(lockout_s)
        self.max_lockout_s = float(max_lockout_s)
        self.noun = str(noun)
        self._lock = threading.Lock()
        self._wrong = 0  # consecutive wrong tries since the last right PIN or lockout start
        self._lockouts = 0  # lockouts in a row (doubling)
        self._locked_until = -math.inf
        self._locked_since: float | None = None
        self.total_wrong = 0  # every wrong try (including those refused while locked)

    def locked_for(self, now: float) -> float:
        """Seconds (>= 0) until the PIN can be tried again; 0 when not locked."""
        with self._lock:
            return max(0.0, self._locked_until - float(now))

    def locked_since(self, now: float) -> float | None:
        """Session time the current lockout began, or None when not locked."""
        with self._lock:
            return self._locked_since if self._locked_until > float(now) else None

    def check(self, pin: str, now: float) -> CommandResult:
        """Check one try at ``now`` (session s). ``ok`` for the right PIN outside a lockout;
        otherwise refused with one line (tries left, or how long the lockout still lasts)."""
        now = float(now)
        right = hmac.compare_digest(str(pin).encode(), self._pin)
        with self._lock:
            left = self._locked_until - now
            if left > 0:
                if not right:
                    self.total_wrong += 1
                return CommandResult(False, f"{self.noun} locked for {math.ceil(left)} s after "
                                            f"{self.max_tries} wrong tries")
            if right:
                self._wrong = 0
                self._lockouts = 0
                self._locked_since = None
                return CommandResult(True, f"{self.noun} accepted")
            self._wrong += 1
            self.total_wrong += 1
            if self._wrong >= self.max_tries:
                dur = min(self.max_lockout_s, self.lockout_s * (2 ** self._lockouts))
                self._lockouts += 1
                self._wrong = 0
                self._locked_until = now + dur
                self._locked_since = now
                return CommandResult(False, f"{self.noun} locked for {math.ceil(dur)} s after {self.max_tries} wrong tries")
            left_tries = self.max_tries - self._wrong
            next_dur = min(self.max_lockout_s, self.lockout_s * (2 ** self._lockouts))
            return CommandResult(False, f"wrong {self.noun} ({left_tries} tr{'y' if left_tries == 1 else 'ies'} left "
                                        f"before a {math.ceil(next_dur)} s lockout)")


class ControlArbiter:
    """Which browser client is in control (``controller`` None: nobody). Thread-safe."""

    def __init__(self):
        self._lock = threading.Lock()
        self._controller: str | None = None
        self._label = ""
        self._since: float | None = None

    @property
    def controller(self) -> str | None:
        with self._lock:
            return self._controller

    def is_controller(self, client_id: str) -> bool:
        with self._lock:
            return self._controller is not None and self._controller == str(client_id)

    def claim(self, client_id: str, label: str, now: float) -> tuple[str | None, str]:
        """Make ``client_id`` the controller (the caller checked the PIN); returns the previous
        ``(controller, label)``."""
        with self._lock:
            prev = (self._controller, self._label)
            if self._controller != str(client_id):
                self._since = float(now)
            self._controller, self._label = str(client_id), str(label)
            return prev

    def release(self, client_id: str) -> bool:
        """Give up control if ``client_id`` holds it; True if it did."""
        with self._lock:
            if self._controller is None or self._controller != str(client_id):
                return False
            self._controller, self._label, self._since = None, "", None
            return True

    def summary(self, pin_locked_s: float = 0.0) -> ControlSummary:
        with self._lock:
            return ControlSummary(self._controller, self._label, self._since, float(pin_locked_s))


class GuardedSession(Protocol):
    """What a :class:`ClientSession` needs of the session it guards (``Session`` has it all)."""

    config: object

    def is_in_control(self, client_id: str) -> bool: ...

    def claim_control(self, client_id: str, pin, label: str = "") -> CommandResult: ...

    def release_control(self, client_id: str) -> CommandResult: ...

    def estop(self) -> CommandResult: ...


class ClientSession:
    """One browser client's view of a :class:`~monotracker.engine.session.Session`.

    Reads (:data:`READS`: ``snapshot``, ``volume``, ``latest_frame``, ``subscribe``,
    ``audit_entries``, ...) are forwarded as is; ``config`` is a copy with the PIN masked. Every
    other public method of the session is a command: it runs only while this client is in
    control, else it returns ``CommandResult(False, NOT_IN_CONTROL)`` (so a command added to
    Session later is guarded by default); other attributes are not reachable. ``estop()`` always runs, from every
    client. ``claim_control``/``release_control`` act for this client only.
    """

    #: methods and attributes forwarded without a control check (they change nothing)
    READS = frozenset({
        "snapshot", "volume", "latest_frame", "subscribe", "audit_entries", "plan_copy", "wait_for_job",
        "plan_path", "session_id", "home", "clock", "control_summary", "is_in_control",
        "latest_pose", "robot_status", "needle_target", "recent_alerts", "latencies_s", "truth_T_base_ct",
        "wait_for_layout",
    })
    #: commands every client may always run
    ALWAYS = frozenset({"estop", "request_estop"})

    def __init__(self, session: GuardedSession, client_id: str):
        object.__setattr__(self, "_session", session)
        object.__setattr__(self, "client_id", str(client_id))

    def __repr__(self) -> str:
        return f"ClientSession({self.client_id!r})"

    def __setattr__(self, name, value):
        raise AttributeError("a ClientSession is read-only; call its commands")

    @property
    def config(self):
        """A copy of the session's configuration with ``arm_pin`` masked."""
        import dataclasses

        return dataclasses.replace(self._session.config, arm_pin="****")

    @property
    def in_control(self) -> bool:
        """True while this client is the one in control."""
        return self._session.is_in_control(self.client_id)

    def claim_control(self, client_id: str | None = None, pin: str = "", label: str = "") -> CommandResult:
        """Take control for this client (``client_id`` may be omitted or must be this client's)."""
        if client_id is not None and str(client_id) != self.client_id:
            return CommandResult(False, "a client can only take control for itself")
        return self._session.claim_control(self.client_id, pin, label)

    def release_control(self, client_id: str | None = None) -> CommandResult:
        """Give up control (also on disconnect)."""
        if client_id is not None and str(client_id) != self.client_id:
            return CommandResult(False, "a client can only release its own control")
        return self._session.release_control(self.client_id)

    def for_client(self, client_id: str) -> "ClientSession":
        if str(client_id) != self.client_id:
            raise PermissionError("a client session cannot act for another client")
        return self

    def estop(self) -> CommandResult:
        """Emergency stop: always allowed, from every client."""
        return self._session.estop()

    def request_estop(self) -> None:
        """The stop channel alone (see ``Session.request_estop``): always allowed, from every client."""
        self._session.request_estop()

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        target = getattr(self._session, name)
        if name in self.READS:
            return target
        if not callable(target):
            raise AttributeError(f"{name} is not available to a browser client")
        session, cid = self._session, self.client_id

        def guarded(*args, **kwargs):
            if not session.is_in_control(cid):
                return CommandResult(False, NOT_IN_CONTROL)
            return target(*args, **kwargs)

        guarded.__name__ = name
        guarded.__doc__ = getattr(target, "__doc__", None)
        return guarded


class Access:
    """The session's part for who may drive it (see the module docstring). Collaborators: the
    operator ``pin``, the event bus and alarm board, the session ``clock`` (s) and the session the
    per-client proxies guard."""

    def __init__(self, pin: str, *, events, alarms, clock, session: GuardedSession):
        self._pin_guard = PinGuard(pin)
        self._control = ControlArbiter()
        self._bus = events
        self._alarm_board = alarms
        self.clock = clock
        self._session = session

    def check_pin(self, pin, refused_code: str, what: str) -> CommandResult:
        """One PIN try through the shared :class:`PinGuard`: an audit row per wrong try (never the
        PIN), one ``pin_lockout`` alert when a lockout starts."""
        now = float(self.clock())
        was_locked = self._pin_guard.locked_for(now) > 0
        r = self._pin_guard.check("" if pin is None else str(pin), now)
        if r.ok:
            return r
        self._bus.event(refused_code, f"{what} refused: {r.message}", {"total_wrong": self._pin_guard.total_wrong},
                        level="warning")
        locked_s = self._pin_guard.locked_for(now)
        self._sync_pin_alarm(now)
        if locked_s > 0 and not was_locked:
            self._bus.alert("alarm", "pin_lockout", f"PIN locked for {locked_s:.0f} s after "
                            f"{self._pin_guard.max_tries} wrong tries", {"locked_s": locked_s})
        return r

    def _sync_pin_alarm(self, now: float) -> float:
        """``pin_lockout`` is active while the PIN is locked; returns the seconds left."""
        left = self._pin_guard.locked_for(now)
        if left > 0:
            self._alarm_board.set("pin_lockout", f"PIN locked for {left:.0f} s after {self._pin_guard.max_tries} "
                                  "wrong tries (arming and taking control)", now)
        else:
            self._alarm_board.clear("pin_lockout", now)
        return left

    def claim_control(self, client_id: str, pin, label: str = "") -> CommandResult:
        """Make browser client ``client_id`` the one in control (taking over from another client).

        ``pin``: the operator PIN (same guard and lockout as arming). ``label``: a display name for
        the other stations ("OR laptop", "nurse tablet"). Refused with one line on a wrong PIN or
        while locked. Already in control: ok without a PIN check."""
        client_id = str(client_id)
        if not client_id:
            return CommandResult.refused("a client id is needed to take control")
        if self._control.is_controller(client_id):
            return CommandResult.done("already in control")
        r = self.check_pin(pin, "control_refused", "taking control")
        if not r.ok:
            return r
        prev, prev_label = self._control.claim(client_id, label, float(self.clock()))
        took = f" from {prev_label or prev}" if prev is not None else ""
        self._bus.event("control_taken", f"{label or client_id} took control{took}",
                        {"client": client_id, "label": label, "previous": prev, "previous_label": prev_label})
        return CommandResult.done("in control" + took)

    def release_control(self, client_id: str) -> CommandResult:
        """Client ``client_id`` gives up control (also when it disconnects); others stay unaffected."""
        if not self._control.release(str(client_id)):
            return CommandResult.done("not in control")
        self._bus.event("control_released", f"client {client_id} released control", {"client": str(client_id)})
        return CommandResult.done("control released")

    def is_in_control(self, client_id: str) -> bool:
        """True if browser client ``client_id`` is the one in control."""
        return self._control.is_controller(str(client_id))

    def control_summary(self):
        """:class:`~monotracker.engine.snapshot.ControlSummary` now (also in ``snap.control``)."""
        return self._control.summary(self._sync_pin_alarm(float(self.clock())))

    def for_client(self, client_id: str) -> ClientSession:
        """The session as browser client ``client_id`` may drive it (see ``engine/access.py``):
        reads as is, commands only while in control, ``estop()`` always."""
        return ClientSession(self._session, str(client_id))

    def report_login_lockout(self, locked_s: float, message: str = "") -> None:
        """The page login (``ui/remote_login.py``, ``serve --allow-remote``) is locked for
        ``locked_s`` s after wrong passwords (> 0: the ``login_lockout`` alarm is active with
        ``message``, and an alert is written when it begins) or no longer locked (0: cleared)."""
        now = float(self.clock())
        if locked_s > 0:
            if self._alarm_board.set("login_lockout", message, now):
                self._bus.alert("alarm", "login_lockout", message, {"locked_s": float(locked_s)})
        else:
            self._alarm_board.clear("login_lockout", now)
