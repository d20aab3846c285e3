"""Online estimate of the detector's image noise (px) from registration residuals.

One frame's residuals give ``sigma^2 = RSS / dof`` with ``dof = 2k - 6`` (k matched fiducials);
with 9 fiducials that is 12 dof, a relative spread of about 20 % in sigma, and with 4 fiducials
only 2 dof (the estimate can be near zero by chance). The detector's noise changes slowly, so
:class:`OnlineNoise` pools the residual sums of squares of the recent accepted frames:
``sigma_pool^2 = sum RSS / sum dof`` (a dof-weighted pooled variance, unbiased, no floor).

Rules (choices written down here):

* **No floor that hides low noise**: with enough pooled dof the pooled value is used as is.
* **Nothing hides high noise**: if the current frame's variance is larger than the pool's by
  more than the F-distribution's ``1 - alpha`` quantile for (frame dof, pool dof), the noise
  went up now (blur, an occluder's edge, a bad ball); the frame's own estimate is used.
* **Few dof, no history**: until ``min_dof`` residual dof are pooled (first frames, few balls)
  the estimate is ``max(pooled, prior_px)``: conservative where the data cannot say.
* **Degrees of freedom**: a sigma estimated from few residuals may be low by chance (12 dof:
  ~20 % spread). ``upper_px`` is its one-sided 95 % upper confidence bound,
  ``sigma sqrt(dof / chi2_0.05(dof))`` (x1.51 at 12 dof, x1.07 at 360); the pose stream gates
  on the TRE predicted with it, and reports the calibrated one (``sigma_px``).
* **The prior is not a measurement**: where the prior stands in (source "prior"), the upper
  bound is the larger of the prior and the residuals' own upper bound for their dof, not the
  prior widened as if it had been measured from those few dof (x2.37 at 4 dof, x1.85 at 6: a
  first frame of 5 balls was gated at 0.71 px where the prior says 0.3 and its residuals 0.1).
  The prior is itself the pessimistic value the data cannot yet rule out; residuals that say
  more still raise the bound (docs/vision.md, "The first frame's noise bound").
* Frames whose fiducials were found inconsistent (a moved ball) enter only after that ball was
  excluded (the caller feeds the residuals of the final fit).

Units: px (equivalent pinhole pixels, as the registration's residuals).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from monotracker.registration.quantiles import chi2_ppf, f_ppf


@dataclass(frozen=True)
class NoiseEstimate:
    """``sigma_px`` the noise to use; ``frame_px`` this frame's own estimate; ``pooled_px`` the
    pool's (including this frame); ``dof`` behind ``sigma_px``; ``source`` one of "pooled",
    "frame" (noise rose), "prior" (too few dof yet); ``upper_px`` its 95 % upper bound."""

    sigma_px: float
    frame_px: float
    pooled_px: float
    dof: int
    source: str
    #: the prior (px) where it stands in (source "prior"), else nan
    prior_px: float = float("nan")

    @property
    def upper_px(self) -> float:
        """One-sided 95 % upper confidence bound of the noise (px), given ``dof``."""
        return self.upper(0.95)

    def upper(self, confidence: float = 0.95) -> float:
        """One-sided upper confidence bound of the noise (px) at ``confidence`` (0.5 ~ the
        estimate itself), given ``dof``: ``sigma sqrt(dof / chi2_(1 - confidence)(dof))``; where
        the prior stands in, the larger of the prior and that bound of the residuals' own
        (pooled) estimate (module docstring)."""
        widen = float(np.sqrt(self.dof / chi2_ppf(1.0 - confidence, self.dof))) if self.dof > 0 else float("nan")
        if self.source == "prior" and np.isfinite(self.prior_px):
            data = self.pooled_px * widen if self.dof > 0 and np.isfinite(self.pooled_px) else 0.0
            return float(max(self.prior_px, data))
        if self.dof <= 0 or not np.isfinite(self.sigma_px):
            return float("nan")
        return float(self.sigma_px * widen)


class OnlineNoise:
    """Pooled residual variance over the last ``window`` accepted frames (see module docstring)."""

    def __init__(self, window: int = 30, min_dof: int = 10, prior_px: float = 0.3, alpha: float = 0.01,
                 prior_is_bound: bool = True):
        self.window = int(window)
        self.min_dof = int(min_dof)
        self.prior_px = float(prior_px)
        self.alpha = float(alpha)
        #: where the prior stands in, its upper bound is the prior itself (or the residuals' own,
        #: if larger); False: the prior widened as if measured from the frame's dof (the rule
        #: before 2026-12-01's twenty-first session, for comparison)
        self.prior_is_bound = bool(prior_is_bound)
        self._frames: deque = deque(maxlen=self.window)

    def reset(self) -> None:
        self._frames.clear()

    @property
    def pooled_dof(self) -> int:
        return int(sum(d for _, d in self._frames))

    def peek(self, rss_px2: float, dof: int) -> NoiseEstimate:
        """The estimate for a frame with residual sum of squares ``rss_px2`` (px^2) and ``dof``,
        without adding it to the pool."""
        dof = int(dof)
        rss = float(rss_px2)
        frame_var = rss / dof if dof > 0 else np.nan
        p_rss = sum(r for r, _ in self._frames)
        p_dof = sum(d for _, d in self._frames)
        tot_dof = p_dof + max(dof, 0)
        pooled_var = (p_rss + (rss if dof > 0 else 0.0)) / tot_dof if tot_dof > 0 else np.nan
        frame_px = float(np.sqrt(frame_var)) if np.isfinite(frame_var) else float("nan")
        pooled_px = float(np.sqrt(pooled_var)) if np.isfinite(pooled_var) else float("nan")
        if tot_dof < self.min_dof:
            cand = [v for v in (pooled_px, self.prior_px) if np.isfinite(v)]
            return NoiseEstimate(max(cand), frame_px, pooled_px, tot_dof, "prior",
                                 self.prior_px if self.prior_is_bound else float("nan"))
        if dof > 0 and p_dof > 0:
            old_var = p_rss / p_dof
            crit = f_ppf(1.0 - self.alpha, dof, p_dof)
            if old_var > 0 and frame_var / old_var > crit:
                return NoiseEstimate(max(frame_px, pooled_px), frame_px, pooled_px, dof, "frame")
        return NoiseEstimate(pooled_px, frame_px, pooled_px, tot_dof, "pooled")

    def update(self, rss_px2: float, dof: int) -> NoiseEstimate:
        """:meth:`peek`, then add the frame to the pool."""
        est = self.peek(rss_px2, dof)
        if dof > 0 and np.isfinite(rss_px2):
            self._frames.append((float(rss_px2), int(dof)))
        return est


# --------------------------------------------------------------------------- centre bias
@dataclass(frozen=True)
class CentreBias:
    """Centre errors that frames of a still head do not average out (issue 28 item 3).

    A detected centre is the true one plus sensor noise (new every frame) plus a bias that stays
    while the scene stays: shading (a ball darker at its limb, lit from one side), a highlight, a
    contact shadow, skin texture and hair near the edge. Measured on the physically rendered
    tuning frames (``benchmarks/camera_pbr.py --fit-bias``), per coordinate, px:

    * ``ball_px``: the part that differs from ball to ball. The pose cannot absorb it, so the
      residuals show it; this value is only the *prior* of that estimate, worth ``prior_dof``
      degrees of freedom (the first frames and 4-5 balls have few of their own);
    * ``common_px``: a shift shared by all balls (the light comes from one side for all of
      them). A pose absorbs a common shift almost entirely, so the residuals never show it;
      it is added to the pose covariance as it is (:func:`~.report.common_shift_covariance`);
    * ``gradient_px``: a bias that changes linearly across the layout (each ball sees the lamp
      and the camera at its own angle on the curved head): ``G u_i`` with ``u_i`` the ball's
      image position about the balls' centroid over their RMS distance from it (unit-free) and
      G a 2x2 matrix whose entries have this standard deviation. A pose absorbs such a field
      too (it is what a small tilt or change of depth does to the image), into its weakest
      directions: on Blender's frames 0.15 px of it put trusted poses 1.0-1.3 mm off at the
      target (:func:`~.report.layout_gradient_covariance`).

    All three scale with the ball's image radius (``*_per_radius``: px of bias per px of
    radius, a shading bias is a fraction of the ball's size) above a floor (``*_px``).
    """

    ball_px: float = 0.0
    ball_per_radius: float = 0.0
    common_px: float = 0.0
    common_per_radius: float = 0.0
    gradient_px: float = 0.0
    gradient_per_radius: float = 0.0
    prior_dof: int = 6
    #: image noise (px per coordinate) assumed for a frame before the pool has measured its own
    noise_prior_px: float = 0.15
    #: where the numbers come from (detector, frame set, date)
    source: str = ""

    def ball_sigma(self, radius_px: float) -> float:
        return float(np.hypot(self.ball_px, self.ball_per_radius * radius_px))

    def common_sigma(self, radius_px: float) -> float:
        return float(np.hypot(self.common_px, self.common_per_radius * radius_px))

    def gradient_sigma(self, radius_px: float) -> float:
        return float(np.hypot(self.gradient_px, self.gradient_per_radius * radius_px))


@dataclass(frozen=True)
class PooledSigma:
    """The per-ball error (px per coordinate) of a fit to pooled centres: ``sigma_px`` (the
    posterior estimate), ``upper_px`` (its upper confidence bound), ``dof`` behind it, ``noise_px``
    (the frame-to-frame noise used), ``source`` ("pooled": data and prior, "data": the residuals
    exceed the prior, so they alone count)."""

    sigma_px: float
    upper_px: float
    dof: int
    noise_px: float
    source: str


def pooled_sigma(rss_px2: float, dof: int, noise_px: float, frames_harmonic: float, prior_ball_px: float,
                 prior_dof: int, confidence: float = 0.95, alpha: float = 0.01) -> PooledSigma:
    """Per-ball error of the pooled centres, ``s^2 = ball^2 + noise^2 / n`` (n frames per ball,
    harmonic mean ``frames_harmonic``): the fit's residuals (``rss_px2`` over ``dof`` = 2k - 6)
    combined with the prior ``prior_ball_px^2 + noise_px^2 / n`` worth ``prior_dof`` (a scaled
    inverse chi-square prior: ``s^2 = (prior_dof s0^2 + rss) / (prior_dof + dof)``). Nothing hides
    a larger error: when the residuals alone exceed the prior beyond the F quantile ``1 -
    alpha``, they are used alone (their own dof). ``upper_px``: ``s sqrt(dof / chi2_(1 -
    confidence)(dof))``."""
    dof = max(int(dof), 0)
    n = max(float(frames_harmonic), 1.0)
    s0 = prior_ball_px**2 + noise_px**2 / n
    rss = float(rss_px2) if np.isfinite(rss_px2) else 0.0
    if dof > 0 and prior_dof > 0 and s0 > 0 and rss / dof / s0 > f_ppf(1.0 - alpha, dof, prior_dof):
        s2, d, src = rss / dof, dof, "data"
    else:
        d = dof + max(int(prior_dof), 0)
        s2 = (max(int(prior_dof), 0) * s0 + rss) / d if d > 0 else s0
        src = "pooled"
    s = float(np.sqrt(max(s2, 0.0)))
    up = s * float(np.sqrt(d / chi2_ppf(1.0 - confidence, d))) if d > 0 else float("inf")
    return PooledSigma(s, up, d, float(noise_px), src)

