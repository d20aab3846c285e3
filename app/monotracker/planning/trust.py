"""How many frames the pose stream will trust, predicted before there is a frame.

The pose stream (:class:`~monotracker.vision.pose_tracker.PoseTracker`) trusts a frame when the
error at the target predicted with an upper bound of its online noise estimate passes its gates
(:class:`~monotracker.vision.tracker_config.TrackerConfig`): the RMS under
``max_predicted_tre_mm``, the probability of more than ``wrong_mm`` under
``max_wrong_probability`` and, where set, of more than ``right_mm`` under
``max_not_right_probability``. All scale with the noise, so for a layout and camera pose there is
one largest noise the gates let through (:func:`gate_noise_px`), and a frame is trusted when the
tracker's noise bound stays under it.

With the default edge-fitted detector the tracker also covers each ball's shading error
(``TrackerConfig.edge_bias_per_rms``, ``edge_common_per_rms``): a ball's centre error is at
least its edge fit's spread, and a shift common to all balls is added; the planner models both
with the planned image noise as the edge spread (:func:`shading_cover`), so the covariance at a
noise bound ``u`` is ``max(u, floor)^2 C1 + C0`` (``C0`` the common shift's), still one largest
``u`` the gates let through.

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
from monotracker.registration.quantiles import chi2_ppf, f_ppf
from monotracker.vision.tracker_config import TrackerConfig, few_ball_factor, tail_problem


def shading_cover(noise_px: float, edge_rms_px: float | None,
                  config: TrackerConfig | None = None, n_balls: int | None = None) -> tuple[float, float]:
    """(per-ball floor px, common shift px) the pose tracker adds for shading when the balls'
    edge fits spread ``edge_rms_px`` (None: the planned image noise ``noise_px``, what the
    default edge-fitted detector shows; 0: a detector without an edge fit, no cover), per
    coordinate: ``TrackerConfig.edge_bias_per_rms`` and ``edge_common_per_rms`` times it, the
    per-ball part times ``few_balls_cover`` when ``n_balls`` (the balls seen; None: many) is at
    most ``few_balls``, as the tracker does for balls it reads as matte; with the kit's balls said
    to be glossy (``TrackerConfig.ball_finish`` ``glossy``) the glossy frames' pair
    (``glossy_few_balls``, ``glossy_few_balls_cover``). With the finish read from each frame (the
    default) the plan cannot know it and predicts as for matte balls: optimistic for glossy balls
    beside their shadows."""
    cfg = config or TrackerConfig()
    e = float(noise_px) if edge_rms_px is None else float(edge_rms_px)
    if not (e > 0):
        return 0.0, 0.0
    per_ball = max(cfg.edge_bias_per_rms, 0.0) * e
    if n_balls is not None:
        per_ball *= max(few_ball_factor(cfg, n_balls, cfg.ball_finish == "glossy"), 0.0)
    return per_ball, max(cfg.edge_common_per_rms, 0.0) * e


def _tails_pass(cov3: np.ndarray, cfg: TrackerConfig) -> bool:
    """The tracker's tail gates on a target covariance (mm^2): its own
    :func:`~monotracker.vision.tracker_config.tail_problem`."""
    return not tail_problem(cov3, cfg)


def _passes(cov3: np.ndarray, cfg: TrackerConfig) -> bool:
    """The tracker's per-frame TRE gates on a target covariance (mm^2): the RMS and the tails."""
    return float(np.sqrt(max(np.trace(cov3), 0.0))) <= cfg.max_predicted_tre_mm and _tails_pass(cov3, cfg)


def gate_noise_px(cov3_per_px2: np.ndarray, config: TrackerConfig | None = None, floor_px: float = 0.0,
                  fixed_cov3: np.ndarray | None = None) -> float:
    """The largest image noise bound ``u`` (px) the tracker's TRE gates let through for the
    target covariance ``max(u, floor_px)^2 cov3_per_px2 + fixed_cov3`` (``cov3_per_px2``: mm^2
    at 1 px of noise, camera frame; ``floor_px``, ``fixed_cov3``: the shading cover of
    :func:`shading_cover`, none by default). 0 when even the floor and the fixed part fail the
    gates (no frame is trusted); inf when no noise can fail them."""
    cfg = config or TrackerConfig()
    cov = np.asarray(cov3_per_px2, float)
    fixed = np.zeros((3, 3)) if fixed_cov3 is None else np.asarray(fixed_cov3, float)
    floor = max(float(floor_px), 0.0)
    rms1 = float(np.sqrt(max(np.trace(cov), 0.0)))
    if rms1 <= 0:
        return float("inf") if _passes(fixed, cfg) else 0.0
    if not _passes(cov * floor**2 + fixed, cfg):
        return 0.0
    room = cfg.max_predicted_tre_mm**2 - float(np.trace(fixed))
    hi = float(np.sqrt(max(room, 0.0))) / rms1        # the RMS gate's limit: no larger u passes
    if hi <= floor:
        return floor
    if _tails_pass(cov * hi**2 + fixed, cfg):
        return hi                                      # (the RMS gate holds at hi by construction)
    lo = floor
    for _ in range(40):   # exceed_probability grows with the noise: bisect for the limit
        mid = 0.5 * (lo + hi)
        if _passes(cov * mid**2 + fixed, cfg):
            lo = mid
        else:
            hi = mid
    return lo


def trusted_fraction(cov3_per_px2: np.ndarray, n_balls: int, noise_px: float, frames: int = 300,
                     config: TrackerConfig | None = None, seed: int = 0, runs: int = 20,
                     floor_px: float = 0.0, fixed_cov3: np.ndarray | None = None) -> float:
    """Expected share of frames the tracker trusts over a run of ``frames`` consecutive frames
    (from the first, warm-up included) with ``n_balls`` matched balls and Gaussian image noise
    ``noise_px`` (px), for a target covariance ``cov3_per_px2`` (mm^2 at 1 px) and the shading
    cover ``floor_px``, ``fixed_cov3`` (:func:`gate_noise_px`): the mean over ``runs`` simulated
    runs (the pool's estimate wanders slowly, so one run says little). 0 when fewer than
    ``min_fiducials`` balls."""
    cfg = config or TrackerConfig()
    dof = 2 * int(n_balls) - 6
    if n_balls < cfg.min_fiducials or dof <= 0:
        return 0.0
    limit = gate_noise_px(cov3_per_px2, cfg, floor_px, fixed_cov3)
    if not (limit > 0):
        return 0.0
    rng = np.random.default_rng(seed)
    ok = 0
    for _ in range(int(runs)):
        rss = noise_px**2 * rng.chisquare(dof, size=int(frames))
        ok += int(np.count_nonzero(_noise_bounds(rss, dof, cfg) <= limit))
    return ok / float(frames * runs)


def _noise_bounds(rss: np.ndarray, dof: int, cfg: TrackerConfig) -> np.ndarray:
    """The noise bound (px) the tracker gates each frame on, for one run of frames with residual
    sums of squares ``rss`` (px^2, in order) and ``dof`` each, from an empty pool: what feeding
    them one by one to :meth:`OnlineNoise.update` with the tracker's settings gives
    (``est.upper(noise_bound_confidence)``, ``est.sigma_px`` where that is not finite), number
    for number (``tests/planning/test_trust.py``), for all frames at once. The pool before frame
    ``i`` holds frames ``i - window .. i - 1`` (every frame enters it); its sum is taken with the
    builtin ``sum`` over the same values in the same order as :meth:`OnlineNoise.peek`, and the
    quantiles are asked once per distinct dof (~200 x faster than the loop: a planned layout asks
    for this ~30 times, 6000 frames each)."""
    pool = OnlineNoise(window=cfg.noise_window, min_dof=cfg.noise_min_dof, prior_px=cfg.noise_prior_px,
                       prior_is_bound=cfg.noise_prior_is_bound)
    r = np.asarray(rss, float)
    n = r.size
    values = r.tolist()
    w = pool.window
    lo = [max(0, i - w) for i in range(n)]
    p_rss = np.array([sum(values[a:i]) for i, a in enumerate(lo)], float)   # builtin sum, as peek
    p_dof = np.array([(i - a) * dof for i, a in enumerate(lo)], np.int64)
    tot_dof = p_dof + dof
    frame_var = r / dof
    frame_px = np.sqrt(frame_var)
    pooled_px = np.sqrt((p_rss + r) / tot_dof)
    # peek's three cases: too few dof (the prior), the noise rose (the frame's), else the pool's
    prior = tot_dof < pool.min_dof
    old_var = np.divide(p_rss, p_dof, out=np.zeros(n), where=p_dof > 0)
    crits = {int(d): f_ppf(1.0 - pool.alpha, dof, int(d)) for d in np.unique(p_dof) if d > 0}
    crit = np.array([crits.get(int(d), np.inf) for d in p_dof], float)
    rose = ~prior & (p_dof > 0) & (old_var > 0)
    rose[rose] = frame_var[rose] / old_var[rose] > crit[rose]
    sigma = np.where(prior, np.maximum(pooled_px, pool.prior_px), np.where(rose, np.maximum(frame_px, pooled_px), pooled_px))
    est_dof = np.where(rose, dof, tot_dof)
    factor = {int(d): np.sqrt(int(d) / chi2_ppf(1.0 - cfg.noise_bound_confidence, int(d)))
              for d in np.unique(est_dof)}
    f = np.array([factor[int(d)] for d in est_dof], float)
    upper = sigma * f
    if pool.prior_is_bound:
        # where the prior stands in: the larger of the prior and the residuals' own bound
        # (NoiseEstimate.upper)
        data = np.where(np.isfinite(pooled_px), pooled_px * f, 0.0)
        upper = np.where(prior, np.maximum(pool.prior_px, data), upper)
    return np.where(np.isfinite(upper), upper, sigma)
