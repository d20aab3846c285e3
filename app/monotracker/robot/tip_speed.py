"""The needle tip's speed as the status panel shows it, from successive tip poses (mm/s).

Both robot rigs (the in-process one and the control-process client) report the arm's status from
states that may repeat between control ticks: the speed is measured only between states with a
strictly later timestamp, and held at its last value otherwise (never reset to 0 by a repeat).
"""

from __future__ import annotations

import numpy as np


class TipSpeed:
    """Tip speed (mm/s) between the last two distinct states; 0 until two have been seen."""

    def __init__(self) -> None:
        self._prev_tip_mm: np.ndarray | None = None
        self._prev_t: float | None = None
        self.mm_s = 0.0

    def update(self, T_base_tip_mm: np.ndarray | None, t_s: float) -> float:
        """Take the tip pose (4x4, base frame, mm; None when unknown) at state time ``t_s`` (s) and
        return the speed (mm/s). A state no later than the last one changes nothing."""
        if T_base_tip_mm is None:
            return self.mm_s
        if self._prev_t is not None and t_s > self._prev_t:
            step_mm = float(np.linalg.norm(T_base_tip_mm[:3, 3] - self._prev_tip_mm[:3, 3]))
            self.mm_s = step_mm / (t_s - self._prev_t)
        if self._prev_t is None or t_s > self._prev_t:
            self._prev_tip_mm, self._prev_t = T_base_tip_mm, t_s
        return self.mm_s
