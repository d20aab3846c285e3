"""The arm backends, in one table: how a robot spec is written, checked and turned into an arm.

A robot spec is ``KIND`` or ``KIND:ARG`` (``"sim"``, ``"ur:192.168.1.10"``). :data:`BACKENDS` has
one row per kind; :func:`spec_problem` checks a spec (``SessionConfig.validate``, the
``serve --robot`` flag), :func:`arm_factory` turns it into a picklable factory of the
:class:`~monotracker.robot.arm.Arm` (the engine calls it in-process, or hands it to the control
process, ``robot/control_process.py``: one path for both). Adding a backend is adding a row
(and its :class:`~monotracker.robot.arm.Arm` subclass).

Units: ``rate_hz`` Hz (the control and RTDE rate: 125 for a UR CB3, 500 for an e-Series);
``q0`` joint angles (rad) where a simulated arm starts.
"""

from __future__ import annotations

import argparse
import functools
from dataclasses import dataclass
from typing import Callable

from monotracker.cli_args import check_ip
from monotracker.errors import InputError


def _sim_arm(arg: str, *, rate_hz: float, seed: int, q0=None):
    from monotracker.robot.sim_arm import SimulatedArm

    return functools.partial(SimulatedArm, q0=q0, period_s=1.0 / rate_hz, seed=seed)


def _ur_arm(arg: str, *, rate_hz: float, seed: int, q0=None):
    from monotracker.robot.ur_rtde_arm import URRTDEArm

    return functools.partial(URRTDEArm, arg, rate_hz=rate_hz)


@dataclass(frozen=True)
class ArmBackend:
    """One arm backend. ``kind`` as written before the colon; ``grammar`` how the whole spec is
    written; ``simulated``: the digital twin's arm (runs on the session clock, starts where the OR
    layout puts it, can simulate a disconnect); ``check_arg(arg)``: None or why the argument is
    wrong; ``factory(arg, rate_hz=, seed=, q0=)``: a picklable callable that makes the arm (a
    simulated arm also takes ``clock=``)."""

    kind: str
    grammar: str
    simulated: bool
    check_arg: Callable[[str], str | None]
    factory: Callable
    describe: str


def _no_arg(arg: str) -> str | None:
    return None if arg == "" else "takes no argument"


BACKENDS: dict[str, ArmBackend] = {
    "sim": ArmBackend("sim", "sim", True, _no_arg, _sim_arm, "the digital twin's UR10 (simulated, on the session clock)"),
    "ur": ArmBackend("ur", "ur:<IP address>", False, check_ip, _ur_arm,
                     "a Universal Robots arm through ur_rtde (RTDE), by IP address: no host names are looked up"),
}
GRAMMAR = " or ".join(f"'{b.grammar}'" for b in BACKENDS.values())


def parse_spec(spec: str) -> tuple[ArmBackend, str]:
    """``(backend, argument)`` of a robot spec; :class:`InputError` with one line when it is wrong."""
    why = spec_problem(spec)
    if why:
        raise InputError(why)
    kind, _, arg = str(spec).partition(":")
    return BACKENDS[kind], arg


def spec_problem(spec) -> str | None:
    """None for a valid robot spec, else one line saying what is wrong."""
    spec = str(spec)
    kind, sep, arg = spec.partition(":")
    backend = BACKENDS.get(kind)
    if backend is None or (sep and backend.check_arg is _no_arg) or (not sep and backend.check_arg is not _no_arg):
        return f"robot must be {GRAMMAR}, not {spec!r}"
    return backend.check_arg(arg)


def arm_factory(spec: str, *, rate_hz: float, seed: int = 0, q0=None):
    """A picklable factory of the arm of ``spec`` (see :class:`ArmBackend`)."""
    backend, arg = parse_spec(spec)
    return backend.factory(arg, rate_hz=rate_hz, seed=seed, q0=q0)


def robot_spec(text: str) -> str:
    """An ``argparse`` type for a robot spec (one line on a bad one)."""
    why = spec_problem(text)
    if why:
        raise argparse.ArgumentTypeError(why)
    return text
