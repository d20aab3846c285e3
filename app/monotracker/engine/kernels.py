"""The package's compiled kernels, compiled ahead of use (``monotracker compile-kernels``).

numba compiles each kernel the first time a process calls it and keeps the machine code in its
disk cache (:mod:`monotracker.registration.compiled`); later processes load it in milliseconds.
After an install (a fresh clone, an upgraded package, a new machine) the cache is empty, and the
first compile costs ~50 CPU s in all on a 2-core machine (measured 2026-11-29: vision 20 s, CT
blob statistics 17 s, CT ball fits 8 s, pose refinement 2.6 s). Left to first use, that lands on
the first CT detection and the first camera frames of the app (the sample CT's detection 20.0 s
against 4.6 s cached; a 2 s headless demo 55.6 s of wall time against 6.8 s). So the installer
(``scripts/setup.sh``) compiles them first, in two processes side by side (~31 s on 2 cores):
:data:`GROUPS` splits the kernels into halves of about equal cost. For the test suite it is
about neutral: its two workers had compiled ~46 CPU s between them, about once.

One table: a group's name, what it covers, and the ``warm_up`` functions that compile (or load)
its kernels for the argument types the product passes.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class KernelGroup:
    """Kernels compiled together: ``warm_ups`` are ``"module:function"`` names (each compiles
    or loads its module's kernels on a tiny input); ``what`` says what uses them."""

    name: str
    what: str
    warm_ups: tuple[str, ...]


#: every compiled kernel of the package, in two groups of about equal first-compile cost
GROUPS: tuple[KernelGroup, ...] = (
    KernelGroup("camera", "the camera path: ball edge fits and the pose refinement",
                ("monotracker.vision.edge_kernels:warm_up", "monotracker.registration.pnp_kernels:warm_up")),
    KernelGroup("ct", "CT fiducial detection: blob statistics and ball fits",
                ("monotracker.ct.sphere_fit:warm_up",)),
)


def group_names() -> tuple[str, ...]:
    return tuple(g.name for g in GROUPS)


def checked_groups(names=None) -> tuple[str, ...]:
    """The group names ``names`` (None = all) as a tuple; ``ValueError`` naming the first
    unknown one."""
    wanted = group_names() if names is None else tuple(names)
    unknown = [n for n in wanted if n not in group_names()]
    if unknown:
        raise ValueError(f"unknown kernel group {unknown[0]!r} (groups: {', '.join(group_names())})")
    return wanted


def compile_groups(names=None, on_done=None) -> list[tuple[str, float]]:
    """Compile (or load from numba's cache) the kernels of the groups ``names`` (None = all), in
    this process, one after another. ``on_done(name, seconds)`` is called after each group.
    Returns ``[(name, seconds)]``. Raises ``ValueError`` naming an unknown group."""
    wanted = checked_groups(names)
    out = []
    for g in GROUPS:
        if g.name not in wanted:
            continue
        t0 = time.monotonic()
        for ref in g.warm_ups:
            mod, fn = ref.split(":")
            getattr(importlib.import_module(mod), fn)()
        dt = time.monotonic() - t0
        out.append((g.name, dt))
        if on_done is not None:
            on_done(g.name, dt)
    return out
