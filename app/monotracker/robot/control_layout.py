"""Shared-memory layout of the control process's slots (target in, heartbeat, state out) and
the state it publishes (:class:`ControlState`); used by both sides of
:mod:`monotracker.robot.control_process`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

STATES = ("disarmed", "armed", "tracking", "holding", "estopped")
PROGRAM_FAULTS = ("", "watchdog", "pendant", "paused", "protective_stop", "emergency_stop",
                  "safeguard_stop", "not_running")

#: target slot: T (16, mm), stamp, valid, head_set (0 none, 1 target frame, 2 base frame), centre (3, mm), radius (mm)
TARGET_N = 16 + 2 + 1 + 3 + 1
#: the engine's heartbeat slot: [monotonic time of the last beat]
HEART_N = 1
#: the stop channel's request slot: [request number, monotonic time the engine signalled it];
#: written by :meth:`ControlProcess.signal_estop` just before it sets the shared e-stop event
STOP_N = 2
#: state slot fields (name, size), in order
STATE_FIELDS = (
    ("t", 1), ("state", 1), ("connected", 1), ("q", 6), ("dq", 6), ("dq_cmd", 6), ("T_tip", 16),
    ("has_target", 1), ("T_target", 16), ("tip_error_mm", 1), ("angle_error_deg", 1),
    ("target_age_s", 1), ("sigma_min", 1), ("step_cost_ms", 1), ("overruns", 1), ("keepout", 1),
    ("program_fault", 1), ("target_stamp", 1), ("worst_cycle_ms", 1), ("true_q", 6), ("true_dq", 6),
    ("cycles", 1), ("t_published", 1), ("stopping", 1),
    # the stop channel's acknowledgement: the newest request number latched by the e-stop
    # watcher, when it latched it (the stop command sent to the arm), and the first control
    # cycle after it with the arm standing still (NaN until then); monotonic s
    ("estop_ack", 1), ("estop_ack_t", 1), ("still_t", 1),
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
    :data:`STATES`; ``program_fault`` one of :data:`PROGRAM_FAULTS`. ``estop_ack``: the newest
    stop request number the control process latched (0: none yet); ``estop_ack_t`` when it did
    (its clock, ``time.monotonic``); ``still_t`` the first control cycle after it in which the arm
    stood still (NaN until then)."""

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
    estop_ack: int = 0
    estop_ack_t: float = float("nan")
    still_t: float = float("nan")


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
        estop_ack=int(g("estop_ack")) if np.isfinite(g("estop_ack")) else 0,
        estop_ack_t=float(g("estop_ack_t")), still_t=float(g("still_t")),
    )
