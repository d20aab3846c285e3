"""Cycle pacing for the tracker's real-time loops (the in-process thread,
:meth:`Tracker.start`, and the control process, :mod:`monotracker.robot.control_child`): one
cycle every ``tracker.period`` seconds on ``tracker.clock``."""

from __future__ import annotations

import time
from typing import Callable


def run_paced(tracker, running: Callable[[], bool], cycle: Callable[[float], bool | None]) -> None:
    """Call ``cycle(t_start)`` every ``tracker.period`` s while ``running()``; stop early when a
    cycle returns False. Each start time goes to ``tracker.cycle_starts``; the slowest cycle to
    ``tracker.worst_cycle_ms``; a cycle that ends past its deadline is reported
    (``tracker._report_overrun``), and one more than a period late re-phases the schedule rather
    than bursting to catch up. Waits with the arm's own pacing (ur_rtde
    ``initPeriod``/``waitPeriod``) when it has one, else sleeps."""
    clock, period = tracker.clock, tracker.period
    nxt = clock()
    while running():
        t_start = clock()
        tracker.cycle_starts.append(t_start)
        token = tracker._begin_cycle()
        if cycle(t_start) is False:
            return
        nxt += period
        t_end = clock()
        tracker.worst_cycle_ms = max(tracker.worst_cycle_ms, (t_end - t_start) * 1e3)
        delay = nxt - t_end
        if delay < 0:
            tracker._report_overrun(-delay)
        if delay < -period:  # overrun: re-phase rather than bursting
            nxt = clock()
        elif delay > 0 and not tracker._wait_cycle(token):
            time.sleep(delay)
