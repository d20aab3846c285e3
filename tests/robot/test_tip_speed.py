"""TipSpeed: the status panel's tip speed from repeated and distinct arm states (hand-checked)."""

import numpy as np

from monotracker.robot.tip_speed import TipSpeed


def tip(x_mm, y_mm=0.0, z_mm=0.0):
    T = np.eye(4)
    T[:3, 3] = (x_mm, y_mm, z_mm)
    return T


def test_speed_between_distinct_states_held_over_repeats_and_unknown_tips():
    s = TipSpeed()
    assert s.update(tip(0.0), 1.0) == 0.0                  # one state: no speed yet
    assert s.update(tip(3.0, 4.0), 1.5) == 10.0             # 5 mm in 0.5 s
    assert s.update(tip(9.0, 9.0), 1.5) == 10.0             # same timestamp (a repeated state): held
    assert s.update(tip(9.0, 9.0), 1.2) == 10.0             # an older state: held, not negative
    assert s.update(None, 2.0) == 10.0                      # tip unknown: held
    assert s.update(tip(3.0, 4.0, 2.0), 2.5) == 2.0         # measured from the last distinct state (t 1.5)
    assert s.mm_s == 2.0
