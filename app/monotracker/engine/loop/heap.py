"""Python's cyclic garbage collector kept out of the pose stream's way while a camera runs.

A full (generation 2) collection walks every object the process holds: with a CT, a plan, the
web server and the numeric libraries loaded that is ~150 000 objects and 60-90 ms on the
project's 2-core machines, with every thread stopped. Taken inside a frame it makes that pose
~90 ms late (measured in the headless demo: one frame of 100 ms, the pose 140 ms old, the arm
holding 0.3-0.4 s under its freshness rules). :class:`HeapFreeze` collects once when a camera
starts and then moves every object alive into the collector's permanent generation
(:func:`gc.freeze`): the collections during tracking walk only what was made since, a few hundred
objects. When the last running camera stops the heap is unfrozen (:func:`gc.unfreeze`), so
garbage cycles made before (an old CT, a closed rig) are collected again.

The freeze is process-wide (one collector): it counts the cameras holding it, so sessions in one
process (tests, a library user's several sessions) share it. ``SessionConfig.freeze_heap``
(True) turns it off for a session. Objects freed by reference counting (most of them: arrays,
frames) are freed as before; only cycles wait until the heap is unfrozen.
"""

from __future__ import annotations

import gc
import threading
import time

_lock = threading.Lock()
_holders = 0


def holders() -> int:
    """How many running cameras hold the heap frozen now."""
    with _lock:
        return _holders


class HeapFreeze:
    """One camera's hold on the frozen heap: :meth:`hold` when it starts, :meth:`release` when it
    stops (both idempotent). ``enabled`` False: neither does anything."""

    def __init__(self, enabled: bool = True):
        self.enabled = bool(enabled)
        self.held = False

    def hold(self) -> float:
        """Freeze the heap (the first holder collects first); returns the seconds it took (0.0
        when already held or off)."""
        global _holders
        if not self.enabled or self.held:
            return 0.0
        t0 = time.perf_counter()
        with _lock:
            if _holders == 0:
                gc.collect()      # what is garbage now is not frozen
                gc.freeze()
            _holders += 1
            self.held = True
        return time.perf_counter() - t0

    def release(self) -> None:
        """Give up this camera's hold; the last one unfreezes the heap."""
        global _holders
        if not self.held:
            return
        with _lock:
            _holders -= 1
            self.held = False
            if _holders == 0:
                gc.unfreeze()
