"""How many frames the pose stream will trust, predicted before there is a frame.

The pose stream (:class:`~monotracker.vision.pose_tracker.PoseTracker`) trusts a frame when the
error at the target predicted with an upper bound of its online noise estimate passes two gates
(:class:`~monotracker.vision.pose_tracker.TrackerConfig`): the RMS under
``max_predicted_tre_mm`` and the probability of more than ``wrong_mm`` under
``max_wrong_probability``. Both scale with the noise, so for a layout and camera pose there is
one largest noise the gates let through (:func:`gate_noise_px`), and a frame is trusted when the
tracker's noise bound stays under it.

The bound comes from :class:`~monotracker.registration.noise.OnlineNoise` pooling the frames'
residual sums of squares; with Gaussian image noise each frame's sum is ``sigma^2 chi2(2k - 6)``.
:func:`trusted_fraction` feeds such draws (a fixed seed) through the real ``OnlineNoise`` with
the tracker's settings and applies the real gates: the same model the tracker runs, frame for
frame, without images. What it leaves out: detection failures, motion, a pose that differs from
the planned one.
"""

from __future__ import annotations

import numpy as np

from monotracker.registration.noise import OnlineNoise
from monotracker.registration.report import exceed_probability
from monotracker.vision.pose_tracker import TrackerConfig


def gate_noise_px(cov3_per_px2: np.ndarray, config: TrackerConfig | None = None) -> float:
    """The largest image noise bound (px) the tracker's TRE gates let through, for a target
    covariance ``cov3_per_px2`` (mm^2 at 1 px of noise, camera frame)."""
    cfg = config or TrackerConfig()
    cov = np.asarray(cov3_per_px2, float)
    rms1 = float(np.sqrt(max(np.trace(cov), 0.0)))
    if rms1 <= 0:
        return float("inf")
    s_rms = cfg.max_predicted_tre_mm / rms1
    if exceed_probability(cov * s_rms**2, cfg.wrong_mm) <= cfg.max_wrong_probability:
        return s_rms
    lo, hi = 0.0, s_rms
    for _ in range(40):   # exceed_probability grows with the noise: bisect for the limit
        mid = 0.5 * (lo + hi)
        if exceed_probability(cov * mid**2, cfg.wrong_mm) <= cfg.max_wrong_probability:
            lo = mid
        else:
            hi = mid
    return lo


def trusted_fraction(cov3_per_px2: np.ndarray, n_balls: int, noise_px: float, frames: int = 300,
                     config: TrackerConfig | None = None, seed: int = 0, runs: int = 20) -> float:
    """Expected share of frames the tracker trusts over a run of ``frames`` consecutive frames
    (from the first, warm-up included) with ``n_balls`` matched balls and Gaussian image noise
    ``noise_px`` (px), for a target covariance ``cov3_per_px2`` (mm^2 at 1 px): the mean over
    ``runs`` simulated runs (the pool's estimate wanders slowly, so one run says little). 0 when
    fewer than ``min_fiducials`` balls."""
    cfg = config or TrackerConfig()
    dof = 2 * int(n_balls) - 6
    if n_balls < cfg.min_fiducials or dof <= 0:
        return 0.0
    limit = gate_noise_px(cov3_per_px2, cfg)
    rng = np.random.default_rng(seed)
    ok = 0
    for _ in range(int(runs)):
        pool = OnlineNoise(window=cfg.noise_window, min_dof=cfg.noise_min_dof, prior_px=cfg.noise_prior_px)
        for r in noise_px**2 * rng.chisquare(dof, size=int(frames)):
            est = pool.update(float(r), dof)
            upper = est.upper(cfg.noise_bound_confidence)
            upper = upper if np.isfinite(upper) else est.sigma_px
            ok += bool(upper <= limit)
    return ok / float(frames * runs)
