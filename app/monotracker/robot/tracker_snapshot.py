"""What the :class:`~monotracker.robot.tracker.Tracker` hands out: operator command results and
the state snapshot of each control cycle (poses mm, base frame; angles deg)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monotracker.robot.safety import Transition


@dataclass(frozen=True)
class CommandResult:
    ok: bool
    reason: str


@dataclass(frozen=True)
class TrackerSnapshot:
    """State at the end of the last control step. Poses in mm (base frame), angles in deg."""

    t: float
    state: str
    connected: bool
    variant: str
    q: np.ndarray
    dq: np.ndarray
    dq_cmd: np.ndarray
    T_base_tool0_mm: np.ndarray
    T_base_tip_mm: np.ndarray
    T_base_target_mm: np.ndarray | None
    tip_error_mm: float
    angle_error_deg: float
    target_age_s: float
    stage: str
    sigma_min: float
    last_transition: Transition | None
    warnings: tuple = field(default_factory=tuple)
    step_cost_ms: float = float("nan")
    #: control cycles of the real-time thread that ended after their deadline (so far)
    overruns: int = 0
    #: a head sphere is known: the keep-out (and APF repulsion) can act this cycle
    keepout_active: bool = False
    #: link up but the arm's control program stopped (a UR's ur_rtde script): the cause
    #: (``"watchdog" | "pendant" | "paused" | "protective_stop" | "emergency_stop" |
    #: "safeguard_stop" | "not_running"``), "" while it runs; the operator's reset restarts it
    program_fault: str = ""
    #: one line saying why and what to do ("" while it runs)
    program_fault_reason: str = ""
