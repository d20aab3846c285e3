"""run_paced, the one cycle pacing of the tracker thread and the control process: cycles start on
the period, a cycle more than a period late re-phases the schedule (no burst of catch-up
cycles) and is reported as an overrun, and a cycle returning False ends the loop. Driven on a
hand-stepped clock (no real sleeping), against a schedule worked out by hand."""

import types

import pytest

from monotracker.robot import pacing


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


class _FakeTracker:
    """What run_paced uses of a Tracker; the arm has no pacing of its own (so run_paced sleeps)."""

    def __init__(self, clock, period):
        self.clock, self.period = clock, period
        self.cycle_starts, self.worst_cycle_ms, self.late = [], 0.0, []

    def _begin_cycle(self):
        return None

    def _wait_cycle(self, token):
        return False

    def _report_overrun(self, late_s):
        self.late.append(late_s)


def test_cycles_start_on_the_period_and_an_overrun_rephases(monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(pacing, "time", types.SimpleNamespace(sleep=lambda s: setattr(clock, "t", clock.t + s)))
    tr = _FakeTracker(clock, 0.010)
    costs = [0.002, 0.002, 0.025, 0.002, 0.002]  # the third cycle takes 2.5 periods
    ran = []

    def cycle(t_start):
        if len(ran) == len(costs):
            return False
        clock.t += costs[len(ran)]
        ran.append(t_start)
        return True

    pacing.run_paced(tr, lambda: True, cycle)
    # by hand: 0, 10, 20 (ends at 45: 15 ms past its 30 ms deadline -> re-phase), 45, 55; 65 stops
    assert tr.cycle_starts == pytest.approx([0.0, 0.010, 0.020, 0.045, 0.055, 0.065])
    assert ran == pytest.approx([0.0, 0.010, 0.020, 0.045, 0.055])
    assert tr.late == pytest.approx([0.015])
    assert tr.worst_cycle_ms == pytest.approx(25.0)


def test_stops_when_not_running(monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(pacing, "time", types.SimpleNamespace(sleep=lambda s: setattr(clock, "t", clock.t + s)))
    tr = _FakeTracker(clock, 0.008)
    n = []
    pacing.run_paced(tr, lambda: len(n) < 3, lambda t: n.append(t))
    assert n == pytest.approx([0.0, 0.008, 0.016])
