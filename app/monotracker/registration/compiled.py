"""numba's ``njit(cache=True)`` for the package's compiled kernels (:mod:`.pnp_kernels`,
:mod:`monotracker.vision.edge_kernels`), one place for where the machine code is cached.

The cache works where a module's folder is not writable (a system-wide install run by another
user, a service account without a home): the machine code then goes to a per-user folder under
the temporary directory, and where no cache can be written at all each process compiles for
itself (slower start, same code). Before this, such a run failed at import ("cannot cache
function ...: no locator")."""

from __future__ import annotations

import os
import tempfile

import numba


def compiled(fn, **options):
    """``fn`` compiled with numba (``njit``, with ``options``), its machine code cached on disk
    where possible."""
    try:
        return numba.njit(cache=True, **options)(fn)
    except RuntimeError:
        pass
    if not numba.config.CACHE_DIR:
        numba.config.CACHE_DIR = os.path.join(tempfile.gettempdir(), f"monotracker-numba-{os.getuid()}")
        try:
            return numba.njit(cache=True, **options)(fn)
        except (RuntimeError, OSError):
            pass
    return numba.njit(**options)(fn)


def compiled_inline(fn):
    """A small helper of compiled kernels, inlined into each caller by numba (a call per voxel
    would cost more than its body)."""
    return compiled(fn, inline="always")
