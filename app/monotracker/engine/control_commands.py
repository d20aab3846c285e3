"""The session's browser-client control: the PIN guard, who is in control, per-client proxies.

The rules live in :mod:`monotracker.engine.control`; these are the Session's methods over them.
Mixed into :class:`~monotracker.engine.session.Session`, whose state these methods use."""

from __future__ import annotations

from monotracker.engine.control import ClientSession
from monotracker.engine.plan_commands import _fail, _ok
from monotracker.engine.snapshot import CommandResult


class ControlCommands:
    """The session's browser-client control: the PIN guard, who is in control, per-client proxies (part of :class:`~monotracker.engine.session.Session`)."""

    def _check_pin(self, pin, refused_code: str, what: str) -> CommandResult:
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
            return _fail("a client id is needed to take control")
        if self._control.is_controller(client_id):
            return _ok("already in control")
        r = self._check_pin(pin, "control_refused", "taking control")
        if not r.ok:
            return r
        prev, prev_label = self._control.claim(client_id, label, float(self.clock()))
        took = f" from {prev_label or prev}" if prev is not None else ""
        self._bus.event("control_taken", f"{label or client_id} took control{took}",
                        {"client": client_id, "label": label, "previous": prev, "previous_label": prev_label})
        return _ok("in control" + took)

    def release_control(self, client_id: str) -> CommandResult:
        """Client ``client_id`` gives up control (also when it disconnects); others stay unaffected."""
        if not self._control.release(str(client_id)):
            return _ok("not in control")
        self._bus.event("control_released", f"client {client_id} released control", {"client": str(client_id)})
        return _ok("control released")

    def is_in_control(self, client_id: str) -> bool:
        """True if browser client ``client_id`` is the one in control."""
        return self._control.is_controller(str(client_id))

    def control_summary(self):
        """:class:`~monotracker.engine.snapshot.ControlSummary` now (also in ``snap.control``)."""
        return self._control.summary(self._sync_pin_alarm(float(self.clock())))

    def for_client(self, client_id: str) -> ClientSession:
        """The session as browser client ``client_id`` may drive it (see ``engine/control.py``):
        reads as is, commands only while in control, ``estop()`` always."""
        return ClientSession(self, str(client_id))

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
