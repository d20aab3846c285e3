"""The predicted TRE is calibrated: Monte-Carlo truth against registration on synthetic scenes.

Truth: scenes with exact ellipse centres (``sim.scenes``, OpenCV's projection), Gaussian pixel
noise of known sigma, the true pose; TRE measured at deep targets. The prediction must be within
+-20 % of the Monte-Carlo RMS error from 0.1 to 0.5 px (the former 0.3 px floor made it 3x too
high at 0.1 px; checked below that this test catches that).
"""

import numpy as np
import pytest

from monotracker.registration import register
from monotracker.registration.noise import OnlineNoise
from monotracker.registration.report import LEGACY_SIGMA_FLOOR_PX, tre_mm
from monotracker.sim.scenes import make_scene


def _monte_carlo(noise_px, n_scenes=4, draws=50, legacy_floor=False):
    errs, preds = [], []
    for sc in range(n_scenes):
        rng = np.random.default_rng(500 + sc)
        base = make_scene(rng, noise_px=0.0, ellipse_bias=True)
        target = base.targets_ct[6]                     # 70 mm deep, centred
        for _ in range(draws):
            pts = base.image_points + rng.normal(scale=noise_px, size=base.image_points.shape)
            r = register(base.fiducials_ct, pts, base.K, base.dist, radius_mm=base.radius_mm, prior=base.T_cam_ct)
            assert r.ok, r.reason
            assert r.sigma_dof == 2 * len(r.pairs) - 6
            errs.append(tre_mm(r.T_cam_ct, base.T_cam_ct, target[None])[0])
            sig = max(r.sigma_px, LEGACY_SIGMA_FLOOR_PX) if legacy_floor else None
            preds.append(r.predicted_tre_mm(target, sigma_px=sig))
    return float(np.sqrt(np.mean(np.square(errs)))), float(np.sqrt(np.mean(np.square(preds))))


@pytest.mark.parametrize("noise_px", [0.1, 0.2, 0.3, 0.5])
def test_predicted_tre_within_20_percent_of_monte_carlo(noise_px):
    actual, predicted = _monte_carlo(noise_px)
    assert 0.8 < predicted / actual < 1.2, (noise_px, actual, predicted)


def test_the_old_floor_would_fail_this_test():
    actual, predicted = _monte_carlo(0.1, n_scenes=2, draws=30, legacy_floor=True)
    assert predicted / actual > 2.0


def test_online_noise_pools_and_never_hides_a_rise():
    rng = np.random.default_rng(3)
    est = OnlineNoise(window=30, min_dof=10, prior_px=0.3)
    # first frame, 4 balls (2 dof): too few to trust the data alone -> conservative prior
    first = est.update(float(np.sum(rng.normal(scale=0.05, size=2) ** 2)), 2)
    assert first.source == "prior" and first.sigma_px >= 0.3
    for _ in range(30):                                  # 9 balls, 12 dof, true sigma 0.1 px
        e = est.update(float(np.sum(rng.normal(scale=0.1, size=12) ** 2)), 12)
    assert e.source == "pooled" and abs(e.sigma_px - 0.1) < 0.015     # no floor: low noise is seen
    # the noise rises (blur, an occluder's edge): the frame's own, larger estimate is used at once
    jump = est.peek(float(np.sum(rng.normal(scale=0.5, size=12) ** 2)), 12)
    assert jump.source == "frame" and jump.sigma_px > 0.3
    # a frame that is merely a little noisier than the pool stays with the pool
    calm = est.peek(float(np.sum(np.full(12, 0.12) ** 2)), 12)
    assert calm.source == "pooled"


def test_exceed_probability_matches_closed_forms():
    from scipy.stats import chi2, norm

    from monotracker.registration.report import exceed_probability

    # one dominant direction: P(|z| > r / sigma); isotropic: chi-square with 3 dof
    assert abs(exceed_probability(np.diag([1.0, 1e-10, 1e-10]), 2.0) - 2 * norm.sf(2.0)) < 0.003
    assert abs(exceed_probability(np.eye(3) / 3, 2.0) - chi2.sf(12.0, 3)) < 0.0015
    R = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0]       # rotation-invariant
    C = np.diag([0.5, 0.2, 0.05])
    assert abs(exceed_probability(R @ C @ R.T, 1.5) - exceed_probability(C, 1.5)) < 1e-12


def test_exceed_probability_counts_the_same_draws_as_all_of_them():
    """The estimate looks only at the draws that can exceed the radius: the same count as the
    whole set of draws gives (the brute-force form), for covariances from tiny to large."""
    from monotracker.registration import report

    rng = np.random.default_rng(7)
    for scale in (1e-4, 0.01, 0.1, 0.3, 1.0, 4.0):
        A = rng.normal(size=(3, 3)) * scale
        C = A @ A.T
        w = np.linalg.eigh(C)[0]
        brute = float(np.mean(((report._STD_NORMAL_3D * np.sqrt(np.clip(w, 0, None))) ** 2).sum(1) > 1.5**2))
        assert report.exceed_probability(C, 1.5) == brute
    assert report.exceed_probability(np.zeros((3, 3)), 1.0) == 0.0


def test_the_priors_upper_bound_is_the_prior_unless_the_residuals_say_more():
    """Where the prior stands in (too few dof yet), the gate's upper bound is the larger of the
    prior and the residuals' own upper bound for their dof, not the prior widened as if it had
    been measured from those dof. The bound is checked against the chi-square quantile computed
    here with scipy (a peer library), not the module's own."""
    from scipy.stats import chi2

    est = OnlineNoise(window=30, min_dof=10, prior_px=0.3)
    quiet = est.peek(4 * 0.1**2, 4)                      # 5 balls, residual RMS 0.1 px
    assert quiet.source == "prior" and quiet.sigma_px == 0.3
    factor = np.sqrt(4 / chi2.ppf(0.05, 4))              # x2.37: what the bound used to widen 0.3 by
    assert quiet.upper(0.95) == pytest.approx(0.3)       # 0.1 x 2.37 = 0.24 < the prior
    assert 0.3 * factor > 0.7
    loud = est.peek(4 * 0.25**2, 4)                      # residual RMS 0.25 px: upper 0.59 > prior
    assert loud.source == "prior" and loud.sigma_px == 0.3
    assert loud.upper(0.95) == pytest.approx(0.25 * factor, rel=1e-6)
    above = est.peek(4 * 0.4**2, 4)                      # residuals above the prior: sigma is theirs
    assert above.sigma_px == pytest.approx(0.4) and above.upper(0.95) == pytest.approx(0.4 * factor, rel=1e-6)
    nothing = est.peek(0.0, 0)                           # no residual dof at all: the prior
    assert nothing.upper(0.95) == pytest.approx(0.3)
    widened = OnlineNoise(window=30, min_dof=10, prior_px=0.3, prior_is_bound=False).peek(4 * 0.1**2, 4)
    assert widened.upper(0.95) == pytest.approx(0.3 * factor, rel=1e-6)     # the rule before, kept for comparison
    # with enough pooled dof the bound is the pooled sigma's, as before
    for _ in range(3):
        est.update(12 * 0.1**2, 12)
    pooled = est.peek(12 * 0.1**2, 12)
    assert pooled.source == "pooled"
    assert pooled.upper(0.95) == pytest.approx(0.1 * np.sqrt(48 / chi2.ppf(0.05, 48)), rel=1e-6)
