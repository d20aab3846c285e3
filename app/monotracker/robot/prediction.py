"""Latency compensation for the pose stream (an extension beyond the paper; opt-in,
``Tracker(predict_target=True)`` / ``SessionConfig(predict_target=True)``).

A target reaches the tracker ``now - stamp`` after its camera frame was captured (transport,
detection, registration: ~40-80 ms); a head moving at 15 mm/s is ~1 mm away by then. From the
stamped history of accepted targets :class:`TargetPredictor` estimates the target's body twist
and extrapolates the last target to ``now``; the controller also gets the twist as velocity
feed-forward.

Its own safety bounds (a prediction must never move the arm where no measurement put the head):

* extrapolation horizon capped at ``horizon_s`` (0.15 s); beyond it the prediction stays at
  the horizon (the safety layer's stale-target hold takes over at 0.1 s without a new capture);
* speed caps: a finite-difference twist faster than ``max_speed_m_s`` (0.05 m/s, 3x a fast
  head motion) or ``max_rate_rad_s`` (0.5 rad/s) is not a head moving, it is a jump or a bad
  pose: the velocity is **reset to zero** (not clamped), so the target is the last measurement;
* the predicted offset from the last measurement is capped at ``max_offset_m`` (5 mm) and
  ``max_offset_rad`` (3 deg) (the arc is shortened, not bent);
* a velocity is only used once ``min_samples`` (3) consecutive targets agree (two differences);
  a gap between captures over ``max_gap_s`` (0.1 s, three frames at 30 fps) resets it;
* reset on every rejected target (occlusion, hold, jump, NaN) and whenever the tracker is not
  tracking (the tracker calls :meth:`reset`).

Units inside the robot package: metres, radians, seconds; poses 4x4 (base frame, needle tip).
"""

from __future__ import annotations

import numpy as np


class TargetPredictor:
    def __init__(self, horizon_s: float = 0.15, alpha: float = 0.5, max_speed_m_s: float = 0.05,
                 max_rate_rad_s: float = 0.5, max_offset_m: float = 0.005, max_offset_rad: float = np.radians(3.0),
                 max_gap_s: float = 0.1, min_samples: int = 3, lead_s: float = 0.0, window: int = 4):
        self.horizon_s = float(horizon_s)
        self.alpha = float(alpha)
        self.max_speed_m_s = float(max_speed_m_s)
        self.max_rate_rad_s = float(max_rate_rad_s)
        self.max_offset_m = float(max_offset_m)
        self.max_offset_rad = float(max_offset_rad)
        self.max_gap_s = float(max_gap_s)
        self.min_samples = int(min_samples)
        self.lead_s = float(lead_s)
        self.window = max(2, int(window))
        self.resets = 0
        self.reset()

    def reset(self) -> None:
        """Forget the history: the next targets are used as measured (no extrapolation)."""
        self._last: tuple[np.ndarray, float] | None = None
        self._hist: list[tuple[np.ndarray, float]] = []
        self._n = 0
        self.V = np.zeros(6)
        self.resets = getattr(self, "resets", 0) + 1

    @property
    def active(self) -> bool:
        """A velocity estimate is in use."""
        return self._n >= self.min_samples and bool(np.any(self.V))

    def update(self, T: np.ndarray, stamp: float) -> None:
        """An accepted target ``T`` (4x4, m, base frame) captured at ``stamp`` (s)."""
        from monotracker.robot.lie import log6, relative

        if self._hist:
            T0, s0 = self._hist[-1]
            dt = stamp - s0
            if dt <= 1e-3:
                return  # a re-sent or out-of-order frame: nothing to learn
            if dt > self.max_gap_s:
                self._restart(T, stamp)
                return
            step = log6(relative(T0, T)) / dt  # body twist (omega; v) over one frame
            if (np.linalg.norm(step[3:]) > self.max_speed_m_s
                    or np.linalg.norm(step[:3]) > self.max_rate_rad_s):
                self._restart(T, stamp)  # a jump, not a motion: no extrapolation from it
                return
        self._hist.append((T.copy(), float(stamp)))
        if len(self._hist) > self.window:
            self._hist.pop(0)
        self._last = self._hist[-1]
        self._n += 1
        if len(self._hist) >= 2:
            # the twist over the whole window (a long baseline: pose noise divided by its span),
            # then low-passed
            (Ta, sa), (Tb, sb) = self._hist[0], self._hist[-1]
            V_new = log6(relative(Ta, Tb)) / (sb - sa)
            self.V = V_new if self._n <= 2 else (1 - self.alpha) * self.V + self.alpha * V_new

    def _restart(self, T, stamp) -> None:
        self.reset()
        self._hist = [(T.copy(), float(stamp))]
        self._last = self._hist[-1]
        self._n = 1

    def predict(self, T: np.ndarray, now: float) -> tuple[np.ndarray, np.ndarray]:
        """``(T_predicted, V_feedforward)``: ``T @ exp(V h)`` with ``h = now - stamp`` clipped to
        [0, horizon_s] and the offset capped; ``(T, 0)`` while no velocity is trusted."""
        from monotracker.robot.lie import exp6

        if self._last is None or self._n < self.min_samples:
            return T, np.zeros(6)
        h = float(np.clip(now + self.lead_s - self._last[1], 0.0, self.horizon_s))
        xi = self.V * h
        lin, ang = float(np.linalg.norm(xi[3:])), float(np.linalg.norm(xi[:3]))
        scale = min(1.0, self.max_offset_m / lin if lin > 0 else 1.0, self.max_offset_rad / ang if ang > 0 else 1.0)
        return T @ exp6(xi * scale), self.V.copy()
