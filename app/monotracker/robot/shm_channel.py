"""A one-writer, many-reader shared-memory slot of float64 values guarded by a seqlock.

Used between the engine process and the robot's control process (:mod:`control_process`):
the writer never waits for a reader and a reader never blocks the writer, so a stalled engine
cannot delay the control loop through this channel (and vice versa).

Layout: ``[seq, v0, v1, ...]`` in a ``multiprocessing.RawArray('d')`` (no lock; picklable to a
``spawn`` child). The writer makes ``seq`` odd, writes the values, makes it even again; a reader
copies the values between two reads of an equal, even ``seq`` (else retries). On x86-64 and
aarch64 an aligned float64 store is atomic and numpy's copy is a plain memory copy; CPython's
own calls around it order the stores well enough for this use (values are rechecked with seq).
"""

from __future__ import annotations

import multiprocessing as mp

import numpy as np


class SeqlockSlot:
    """``n`` float64 values plus a sequence number in shared memory.

    ``write(values)`` (one writer only) and ``read() -> (seq, values copy) | None`` (None if no
    value was ever written or a consistent copy could not be taken in ``max_tries``)."""

    def __init__(self, n: int, raw=None):
        self.n = int(n)
        self.raw = raw if raw is not None else mp.RawArray("d", self.n + 1)
        self._a = np.frombuffer(self.raw, dtype=np.float64)
        if self._a.shape != (self.n + 1,):
            raise ValueError(f"shared slot has {self._a.shape[0] - 1} values, expected {self.n}")

    def __getstate__(self):
        return {"n": self.n, "raw": self.raw}

    def __setstate__(self, st):
        self.__init__(st["n"], st["raw"])

    def write(self, values) -> None:
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if v.shape != (self.n,):
            raise ValueError(f"slot takes {self.n} values, got {v.shape[0]}")
        a = self._a
        a[0] = a[0] + 1.0  # odd: writing
        a[1:] = v
        a[0] = a[0] + 1.0  # even: consistent

    @property
    def seq(self) -> float:
        return float(self._a[0])

    def read(self, max_tries: int = 10000):
        a = self._a
        for _ in range(max_tries):
            s1 = float(a[0])
            if s1 == 0.0:
                return None
            if int(s1) % 2:
                continue
            v = a[1:].copy()
            if float(a[0]) == s1:
                return s1, v
        return None
