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
