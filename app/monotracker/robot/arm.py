"""One interface for every arm backend (simulated, real UR through ur_rtde).

Units: rad, rad/s, rad/s^2, seconds. A backend raises :class:`ArmError` (a
:class:`~monotracker.errors.MonoTrackerError`, one-line message) when the arm cannot be reached
or the connection drops; the tracker turns that into a latched e-stop.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from monotracker.errors import MonoTrackerError


class ArmError(MonoTrackerError):
    """The arm does not answer, refused a command, or the connection dropped."""


class ArmProgramStopped(ArmError):
    """The link is up but the arm's control program is not running (a UR: the ur_rtde control
    script was stopped by the RTDE watchdog, the pendant, a protective/emergency stop or a script
    error). Every command is refused until the operator's reset restarts it
    (:meth:`Arm.recover`). ``cause``: ``"watchdog" | "pendant" | "paused" | "protective_stop" |
    "emergency_stop" | "safeguard_stop" | "not_running"``."""

    def __init__(self, message: str, cause: str = "not_running"):
        super().__init__(message)
        self.cause = cause


@dataclass
class ArmState:
    """Measured joint positions ``q`` (rad) and velocities ``dq`` (rad/s) at time ``stamp``."""

    q: np.ndarray
    dq: np.ndarray
    stamp: float


class Arm(ABC):
    """Joint-velocity-controlled 6-axis arm."""

    #: Control period the backend expects commands at (s).
    period_s: float = 1.0 / 125.0

    @abstractmethod
    def connect(self) -> None:
        """Open the connection (raises :class:`ArmError`)."""

    @abstractmethod
    def disconnect(self) -> None:
        """Stop the arm and close the connection (never raises)."""

    @abstractmethod
    def is_connected(self) -> bool: ...

    @abstractmethod
    def read(self) -> ArmState:
        """Latest measured state (raises :class:`ArmError` when disconnected)."""

    @abstractmethod
    def command_velocity(self, dq: np.ndarray, acceleration: float) -> None:
        """Stream a joint velocity (rad/s) reached with at most ``acceleration`` (rad/s^2)."""

    @abstractmethod
    def stop(self, deceleration: float) -> None:
        """Decelerate to standstill (rad/s^2). Safe to call repeatedly and when disconnected."""

    def program_fault(self) -> ArmProgramStopped | None:
        """The reason the arm's control program is not running while the link is up, or None
        (running, or a backend without such a program). Never raises."""
        return None

    def recover(self) -> None:  # noqa: B027 - optional: a backend without a control program has nothing to restart
        """Restart the arm's control program after :meth:`program_fault` (operator's reset only;
        the tracker never calls it while armed). Raises :class:`ArmError` (one line) when it
        cannot, e.g. a protective stop still to be cleared on the pendant. Default: nothing to do."""

    # Cycle pacing: a backend with its own real-time pacing (ur_rtde's initPeriod/waitPeriod)
    # overrides both; the tracker's thread sleeps itself when wait_cycle returns False.
    def begin_cycle(self):
        """Called at the start of each real-time control cycle; returns a token for wait_cycle."""
        return None

    def wait_cycle(self, token) -> bool:
        """Wait for the end of the cycle begun with ``token``; False: not handled here."""
        return False
