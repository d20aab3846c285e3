"""Latency compensation for the pose stream (an extension beyond the paper;
``Tracker(predict_target=True)`` / ``SessionConfig(predict_target=...)``).

A target reaches the tracker ``now - stamp`` after its camera frame was captured (transport,
detection, registration: ~40-80 ms); a head moving at 15 mm/s is ~1 mm away by then. From the
stamped history of accepted targets :class:`TargetPredictor` estimates the target's pose, body
twist and its rate with a constant-acceleration Kalman filter on SE(3) (error state in the body
tangent space; one 3x3 covariance for the rotational and one for the translational components;
white-noise jerk as the process model), and extrapolates the filtered pose to ``now``: the
horizon is the measured latency of the newest target, ``now - stamp``. The controller also gets
the twist at ``now`` as velocity feed-forward. The filter divides the pose-stream jitter
instead of amplifying it as a finite difference does; the jitter itself (the filter's
measurement variance) is learnt from the stream (third differences of evenly spaced targets,
which a smooth head motion hardly enters), so a quiet stream is smoothed less and followed
more closely than a noisy one.

The jerk noise is chosen from the stream (``jerk_choices``): a bank of filters (1x, 3x, 10x the
configured jerk) is fed every target and the prediction continues from the one whose
one-frame-ahead innovations are smallest (:meth:`TargetPredictor._adopt_best`).

Measured (``benchmarks/robot_control.py``, same run): tip RMS at 15 mm/s 1.87 mm without
prediction, 0.56 mm with the earlier finite-difference predictor, 0.36 mm with this filter.

Its own safety bounds (a prediction must never move the arm where no measurement put the head):

* extrapolation horizon capped at ``horizon_s`` (0.15 s); beyond it the prediction stays at
  the horizon (the safety layer's stale-target hold takes over at 0.1 s without a new capture);
* speed caps: a frame-to-frame twist faster than ``max_speed_m_s`` (0.05 m/s, 3x a fast head
  motion) or ``max_rate_rad_s`` (0.5 rad/s) is not a head moving, it is a jump or a bad pose:
  the filter is **reset** (not clamped), so the target is the last measurement; a filtered
  twist over the caps is never used either;
* the predicted offset from the last *measurement* is capped at ``max_offset_m`` (5 mm) and
  ``max_offset_rad`` (3 deg) (the arc is shortened, not bent);
* a velocity is only used once ``min_samples`` (3) consecutive targets agree (two differences);
  a gap between captures over ``max_gap_s`` (0.1 s, three frames at 30 fps) resets it;
* reset on every rejected target (occlusion, hold, jump, NaN) and whenever the tracker is not
  tracking (the tracker calls :meth:`reset`); :meth:`predict` only extrapolates the target the
  filter last saw (any other pose is returned as it is, with no feed-forward).

Units inside the robot package: metres, radians, seconds; poses 4x4 (base frame, needle tip).
Twists are ``(omega; v)`` (rad/s; m/s), in the target's body frame.
"""

from __future__ import annotations

import numpy as np


class TargetPredictor:
    """Constant-acceleration Kalman filter on the stamped targets + bounded extrapolation.

    Args:
        horizon_s: extrapolation cap (s).
        max_speed_m_s, max_rate_rad_s: frame-to-frame speed above which a step is a jump (reset).
        max_offset_m, max_offset_rad: cap of the predicted offset from the last measurement.
        max_gap_s: a capture gap longer than this resets the filter (s).
        min_samples: targets needed before any extrapolation (>= 2).
        lead_s: extra horizon (s) beyond the measured latency (0: the latency only; the
            controller puts the arm on its reference without a lag of its own).
        meas_sigma_m, meas_sigma_rad: pose-stream jitter per frame (1 sigma; m, rad): the
            starting value, and with ``learn_noise`` the centre of the [0.1x, 10x] range the
            learnt jitter is kept in.
        jerk_sigma_m_s3, jerk_sigma_rad_s3: the head's jerk as white noise (m/s^3, rad/s^3,
            per sqrt(s)): larger follows changes of speed sooner, smaller filters more (tuned
            on the benchmarks: a 15 mm/s head and breathing).
        speed0_m_s, speed0_rad_s, accel0_m_s2, accel0_rad_s2: prior spreads (1 sigma) of the
            head's speed and acceleration when the filter (re)starts.
        model: ``"ca"`` (constant acceleration) or ``"cv"`` (constant velocity; the
            ``jerk_sigma`` values are then the acceleration's white noise).
        learn_noise: learn the jitter from the stream (else ``meas_sigma`` throughout).
        blend_s: a new frame's correction of the prediction fades in with this time constant
            (s) instead of stepping the target (0: step).
        jerk_choices: multipliers of ``jerk_sigma`` for the bank of filters the prediction
            chooses from (see :meth:`_adopt_best`); one value: a single filter at that
            multiple; none: a single filter at ``jerk_sigma``.
        free_roll: never extrapolate the roll about the needle axis (body z), neither in the
            pose nor in the feed-forward: a needle is symmetric, so the roll is a convention,
            and the engine chooses it to follow the arm's current roll (no needless wrist
            spin); extrapolating that roll would feed back (arm rolls -> target rolls -> a roll
            rate is estimated -> arm rolls faster) up to the rate cap.

    Raises ``ValueError`` for an unknown ``model``.
    """

    def __init__(self, horizon_s: float = 0.15, max_speed_m_s: float = 0.05,
                 max_rate_rad_s: float = 0.5, max_offset_m: float = 0.005, max_offset_rad: float = np.radians(3.0),
                 max_gap_s: float = 0.1, min_samples: int = 3, lead_s: float = 0.0,
                 meas_sigma_m: float = 0.15e-3, meas_sigma_rad: float = np.radians(0.05),
                 jerk_sigma_m_s3: float = 0.02, jerk_sigma_rad_s3: float = 0.05,
                 speed0_m_s: float = 0.02, speed0_rad_s: float = 0.05,
                 accel0_m_s2: float = 0.05, accel0_rad_s2: float = 0.1, model: str = "ca", learn_noise: bool = True,
                 blend_s: float = 0.05, free_roll: bool = True, jerk_choices: tuple = (1.0, 3.0, 10.0)):
        if model not in ("ca", "cv"):
            raise ValueError(f"prediction model must be 'ca' or 'cv', not {model!r}")
        self.model = model
        self.horizon_s = float(horizon_s)
        self.max_speed_m_s = float(max_speed_m_s)
        self.max_rate_rad_s = float(max_rate_rad_s)
        self.max_offset_m = float(max_offset_m)
        self.max_offset_rad = float(max_offset_rad)
        self.max_gap_s = float(max_gap_s)
        self.min_samples = max(2, int(min_samples))
        self.lead_s = float(lead_s)
        # per component group (rotation, translation): measurement variance, process density
        self._r0 = np.array([meas_sigma_rad ** 2, meas_sigma_m ** 2], dtype=float)
        self._r = self._r0.copy()
        self._r_est = self._r0.copy()
        self.learn_noise = bool(learn_noise)
        self.noise_frames = 30.0
        self.blend_s = float(blend_s)
        self.free_roll = bool(free_roll)
        if len(jerk_choices) == 1:  # one filter, at that multiple of the configured jerk noise
            jerk_sigma_m_s3, jerk_sigma_rad_s3 = (jerk_sigma_m_s3 * float(jerk_choices[0]),
                                                  jerk_sigma_rad_s3 * float(jerk_choices[0]))
        self._q = np.array([jerk_sigma_rad_s3 ** 2, jerk_sigma_m_s3 ** 2], dtype=float)
        self._v0 = np.array([speed0_rad_s ** 2, speed0_m_s ** 2], dtype=float)
        self._a0 = np.array([accel0_rad_s2 ** 2, accel0_m_s2 ** 2], dtype=float)
        self.resets = 0
        # one filter per jerk noise (``jerk_choices`` x the configured one), all fed every target;
        # the one whose predictions matched the next targets best lends its state (_adopt_best)
        kw = dict(horizon_s=horizon_s, max_speed_m_s=max_speed_m_s, max_rate_rad_s=max_rate_rad_s,
                  max_offset_m=max_offset_m, max_offset_rad=max_offset_rad, max_gap_s=max_gap_s,
                  min_samples=min_samples, lead_s=lead_s, meas_sigma_m=meas_sigma_m, meas_sigma_rad=meas_sigma_rad,
                  speed0_m_s=speed0_m_s, speed0_rad_s=speed0_rad_s, accel0_m_s2=accel0_m_s2,
                  accel0_rad_s2=accel0_rad_s2, model=model, learn_noise=learn_noise, blend_s=blend_s,
                  free_roll=free_roll, jerk_choices=())
        self._bank = [TargetPredictor(jerk_sigma_m_s3=jerk_sigma_m_s3 * m, jerk_sigma_rad_s3=jerk_sigma_rad_s3 * m, **kw)
                      for m in jerk_choices] if len(jerk_choices) > 1 else []
        self.reset()

    def reset(self) -> None:
        """Forget the history: the next targets are used as measured (no extrapolation), and the
        bank chooses its filter afresh from what follows."""
        self.score = float("nan")  # low-passed normalised innovation energy (one frame ahead)
        self.jerk_choice = 0  # index into jerk_choices of the filter in use
        self._last: tuple[np.ndarray, float] | None = None  # the last measurement (T, stamp)
        self._T: np.ndarray | None = None  # filtered pose at the last stamp
        self._P = np.zeros((2, 3, 3))  # [group][3x3] covariance of (pose, twist, accel) per component
        self._n = 0
        self._recent: list = []
        self._out = self._blend = None  # last output (T, V, now); fading correction (xi, t0)
        self._fresh = False
        self.V = np.zeros(6)
        self.A = np.zeros(6)
        self.resets = getattr(self, "resets", 0) + 1
        for f in getattr(self, "_bank", ()):
            f.reset()

    @property
    def active(self) -> bool:
        """A velocity estimate is in use."""
        return self._n >= self.min_samples and bool(np.any(self.V))

    def _too_fast(self, xi: np.ndarray) -> bool:
        return bool(np.linalg.norm(xi[3:]) > self.max_speed_m_s or np.linalg.norm(xi[:3]) > self.max_rate_rad_s)

    def update(self, T: np.ndarray, stamp: float) -> None:
        """An accepted target ``T`` (4x4, m, base frame) captured at ``stamp`` (s)."""
        from monotracker.robot.lie import exp6, log6, relative

        if self._bank:
            self._adopt_best(T, stamp)
            return
        if self._last is None:
            self._restart(T, stamp)
            return
        T0, s0 = self._last
        dt = stamp - s0
        if dt <= 1e-3:
            return  # a re-sent or out-of-order frame: nothing to learn
        if dt > self.max_gap_s:
            self._restart(T, stamp)
            return
        step = log6(relative(T0, T)) / dt  # body twist over one frame (finite difference)
        if self._too_fast(step):
            self._restart(T, stamp)  # a jump, not a motion: no extrapolation from it
            return
        self._last = (T.copy(), float(stamp))
        self._n += 1
        if self.learn_noise:
            self._learn_noise(T, float(stamp))
        # predict (constant acceleration, white-noise jerk) ...
        T_pred = self._T @ exp6(self.V * dt + 0.5 * self.A * dt * dt)
        V_pred = self.V + self.A * dt
        F = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
        if self.model == "ca":
            Qn = np.array([[dt ** 5 / 20, dt ** 4 / 8, dt ** 3 / 6], [dt ** 4 / 8, dt ** 3 / 3, dt ** 2 / 2],
                           [dt ** 3 / 6, dt ** 2 / 2, dt]])
        else:  # constant velocity, white-noise acceleration; the acceleration state stays 0
            Qn = np.array([[dt ** 3 / 3, dt ** 2 / 2, 0.0], [dt ** 2 / 2, dt, 0.0], [0.0, 0.0, 0.0]])
        for g in range(2):
            self._P[g] = F @ self._P[g] @ F.T + self._q[g] * Qn
        # ... and correct with the innovation in the predicted body frame
        y = log6(relative(T_pred, T))
        e = float(y[3:] @ y[3:]) / self._r[1] + float(y[:2] @ y[:2]) / self._r[0]  # the roll is free
        self.score = e if not np.isfinite(self.score) else self.score + (e - self.score) / self.noise_frames
        k = np.empty((3, 6))
        for g, sl in ((0, slice(0, 3)), (1, slice(3, 6))):
            P = self._P[g]
            K = P[:, 0] / (P[0, 0] + self._r[g])
            k[:, sl] = K[:, None]
            self._P[g] = P - np.outer(K, P[0, :])
        self._T = T_pred @ exp6(k[0] * y)
        self._fresh = True
        self.V = V_pred + k[1] * y
        self.A = self.A + k[2] * y

    def _adopt_best(self, T: np.ndarray, stamp: float) -> None:
        """Feed every filter of the bank, then continue from the state of the one that has
        predicted the targets best (the lowest ``score``: its one-frame-ahead innovations, each
        normalised by the learnt jitter, low-passed over ``noise_frames``; a filter replaces the
        one in use only when 10 % better, so it does not flicker). How fast the head's speed
        changes differs (a 0.5 Hz nod against a slow drift) and so does the stream's jitter: a
        fixed jerk noise either lags a quickly changing motion on a quiet stream or follows the
        jitter of a noisy one. Every filter has the same bounds and resets, so the choice never
        loosens one; the output still fades a new frame's correction in (``blend_s``)."""
        for f in self._bank:
            f.update(T, stamp)
        cur = self._bank[self.jerk_choice]
        best = min(range(len(self._bank)), key=lambda i: self._bank[i].score if np.isfinite(self._bank[i].score) else np.inf)
        if np.isfinite(self._bank[best].score) and (not np.isfinite(cur.score)
                                                     or self._bank[best].score < 0.9 * cur.score):
            self.jerk_choice = best
        f = self._bank[self.jerk_choice]
        if self._last is not None and f._last is not None and f._last[1] == self._last[1] and f._n == self._n:
            return  # a re-sent or out-of-order frame: nothing new
        self.score = f.score
        self._last = None if f._last is None else (f._last[0].copy(), f._last[1])
        self._T = None if f._T is None else f._T.copy()
        self._P, self._n = f._P.copy(), f._n
        self.V, self.A = f.V.copy(), f.A.copy()
        self._r, self._r_est = f._r.copy(), f._r_est.copy()
        self._fresh = True

    def _learn_noise(self, T: np.ndarray, stamp: float) -> None:
        """Pose-stream jitter from the third differences of four evenly spaced targets (a
        smooth head motion has next to none: 149 mm/s^3 of jerk moves 0.006 mm in three frames
        at 30 fps, the jitter of one pose enters it 20-fold in variance), low-passed over about
        ``noise_frames`` frames and kept within [0.1, 10] x the configured jitter; it sets how
        much the filter smooths (its measurement variance)."""
        from monotracker.robot.lie import log3

        self._recent.append((T[:3, :3].copy(), T[:3, 3].copy(), stamp))
        if len(self._recent) > 4:
            self._recent.pop(0)
        if len(self._recent) < 4:
            return
        gaps = np.diff([x[2] for x in self._recent])
        if gaps.max() > 1.2 * gaps.min():
            return  # uneven frame spacing: a third difference would see the motion
        R0 = self._recent[0][0]
        rot = np.array([log3(R @ R0.T) for R, _, _ in self._recent])
        pos = np.array([p for _, p, _ in self._recent])
        c = np.array([-1.0, 3.0, -3.0, 1.0])
        for g, x in ((0, rot), (1, pos)):
            var = float(np.mean((c @ x) ** 2)) / 20.0
            self._r_est[g] += (var - self._r_est[g]) / self.noise_frames
        self._r = np.clip(self._r_est, 0.01 * self._r0, 100.0 * self._r0)

    def _restart(self, T, stamp) -> None:
        """Start the filter on one measurement: pose ``T``, twist and its rate zero with the
        prior spreads of a head's motion (``speed0``, ``accel0``), so the first frame-to-frame
        differences, noisy over a 33 ms baseline, are shrunk towards standing still rather than
        taken as they are."""
        self.reset()
        self._last = (T.copy(), float(stamp))
        self._T = T.copy()
        for g in range(2):
            self._P[g] = np.diag([self._r[g], self._v0[g], self._a0[g] if self.model == "ca" else 0.0])
        self._n = 1

    def predict(self, T: np.ndarray, now: float) -> tuple[np.ndarray, np.ndarray]:
        """``(T_predicted, V_feedforward)`` for the target ``T`` (the last one given to
        :meth:`update`): the filtered pose extrapolated by ``exp(V h)``, ``h = now - stamp``
        clipped to [0, horizon_s], its offset from ``T`` capped; ``(T, 0)`` while no velocity is
        trusted, when the filtered twist or its extrapolation to ``now`` is over the speed caps, or when ``T`` is not the
        filter's last measurement."""
        from monotracker.robot.lie import exp6, log6, relative

        if self._last is None or self._n < self.min_samples or self._T is None:
            if self._last is not None and np.array_equal(T, self._last[0]):
                self._out = (T.copy(), np.zeros(6), float(now))  # blended from, once active
            return T, np.zeros(6)
        T_meas, stamp = self._last
        if not np.array_equal(T, T_meas) or self._too_fast(self.V):
            self._out = self._blend = None
            return T, np.zeros(6)
        h = float(np.clip(now + self.lead_s - stamp, 0.0, self.horizon_s))
        V = self.V + self.A * h
        if self._too_fast(V):  # the extrapolated twist (with the acceleration) is over the caps too
            self._out = self._blend = None
            return T, np.zeros(6)
        T_raw = self._T @ exp6(self.V * h + 0.5 * self.A * h * h)
        if self._fresh and self._out is not None and 0.0 <= now - self._out[2] <= 0.05:
            # a new measurement moved the prediction: start from where the last output was
            # heading and fade the difference out over blend_s (no step in the target)
            T_o, V_o, t_o = self._out
            self._blend = (log6(relative(T_raw, T_o @ exp6(V_o * (now - t_o)))), float(now))
        self._fresh = False
        if self._blend is not None:
            w = float(np.exp(-(now - self._blend[1]) / self.blend_s)) if self.blend_s > 0 else 0.0
            if w < 1e-3:
                self._blend = None
            else:
                T_raw = T_raw @ exp6(self._blend[0] * w)
        self._out = (T_raw, V, float(now))
        xi = log6(relative(T_meas, T_raw))  # offset from the measurement
        if self.free_roll:
            xi[2] = 0.0  # keep the measured roll about the needle axis (see free_roll)
            V = V.copy()
            V[2] = 0.0
        lin, ang = float(np.linalg.norm(xi[3:])), float(np.linalg.norm(xi[:3]))
        scale = min(1.0, self.max_offset_m / lin if lin > 0 else 1.0, self.max_offset_rad / ang if ang > 0 else 1.0)
        return T_meas @ exp6(xi * scale), V
