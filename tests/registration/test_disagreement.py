"""Each ball's disagreement with the others (registration/disagreement.py) against independent
truths: the linearised leave-one-out error against real refits without the ball (LM from the
true pose), the chi-square law's false-alarm rate on pure noise, and a ball biased by a pixel
named (synthetic scenes: exact ellipse centres plus Gaussian noise)."""

import numpy as np

from monotracker.registration.disagreement import MIN_BALLS, disagreement_cover, leave_one_out_errors
from monotracker.registration.pnp import _residuals_and_jacobian, refine_pose
from monotracker.registration.projection import undistort_to_normalised
from monotracker.sim.scenes import _to_pixels, ellipse_centre_normalised, make_scene


def fitted(seed: int, noise_px: float, bias: tuple = (0, (0.0, 0.0))):
    """(residuals (2k,) px, J (2k, 6), scene, observations normalised, fitted T) of one scene's
    balls seen with Gaussian noise ``noise_px`` and ball ``bias[0]`` moved ``bias[1]`` px."""
    rng = np.random.default_rng(seed)
    s = make_scene(rng, noise_px=0.0, ellipse_bias=True, n_stray=0)
    T = s.T_cam_ct
    Xc = s.fiducials_ct @ T[:3, :3].T + T[:3, 3]
    px = _to_pixels(ellipse_centre_normalised(Xc, s.radius_mm), s.K, s.dist)
    px = px + rng.normal(scale=noise_px, size=px.shape)
    px[bias[0]] += np.asarray(bias[1], float)
    obs = undistort_to_normalised(px, s.K, s.dist)
    fxy = np.array([s.K[0, 0], s.K[1, 1]])
    fit = refine_pose(T, s.fiducials_ct, obs, fxy, s.radius_mm)
    r, J = _residuals_and_jacobian(fit.T[:3, :3], fit.T[:3, 3], s.fiducials_ct, obs, fxy, s.radius_mm)
    return r, J, s, obs, fit.T


def test_the_linearised_error_is_the_refit_without_the_ball():
    """e_i from one fit's residuals equals the error of ball i's projection under the pose
    refitted (LM) without it, to 0.02 px + 3 % (the projection is not linear over the pose
    change one ball makes): the closed form is the leave-one-out."""
    for seed in range(4):
        r, J, s, obs, T = fitted(seed, 0.4, (2, (1.5, -0.8)))
        e, _d2 = leave_one_out_errors(r, J)
        fxy = np.array([s.K[0, 0], s.K[1, 1]])
        for i in range(len(obs)):
            keep = np.arange(len(obs)) != i
            loo = refine_pose(T, s.fiducials_ct[keep], obs[keep], fxy, s.radius_mm)
            ri, _ = _residuals_and_jacobian(loo.T[:3, :3], loo.T[:3, 3], s.fiducials_ct[i:i + 1], obs[i:i + 1], fxy,
                                            s.radius_mm)
            assert np.linalg.norm(e[i] - ri) <= 0.02 + 0.03 * np.linalg.norm(ri), (seed, i, e[i], ri)


def test_pure_noise_flags_balls_at_the_quantiles_rate():
    """With every centre's noise as its cover says (0.3 px), a ball is widened about as often as
    the quantile's tail (1 % at 0.99): over 400 scenes x their balls, 0.4-2 %."""
    flagged, total = 0, 0
    for seed in range(400):
        r, J, *_ = fitted(seed, 0.3)
        out, _ = disagreement_cover(r, J, np.full(len(r), 0.3**2), 0.99)
        flagged += int(np.count_nonzero(out[::2]))
        total += len(r) // 2
    assert 0.004 <= flagged / total <= 0.02, (flagged, total)


def test_a_ball_a_pixel_off_is_covered_by_its_disagreement_and_the_others_are_not():
    """A ball 1.2 px off among balls with 0.15 px noise: its rows' floor is its leave-one-out
    error squared (the bias, 1.2 px, give or take the noise of its prediction, ~0.2 px per
    coordinate: |e| 0.6-1.8 px), the others' stay 0 in most scenes."""
    others = 0
    for seed in range(20):
        r, J, s, *_ = fitted(seed, 0.15, (3, (0.85, 0.85)))
        out, found = disagreement_cover(r, J, np.full(len(r), 0.15**2), 0.99)
        assert 0.6**2 <= out[6] == out[7] <= 1.8**2, (seed, out[6])
        assert found[0] == (3, np.sqrt(out[6])), found            # named, the worst first
        others += int(np.count_nonzero(np.delete(out, [6, 7])))
    assert others <= 20 * (len(s.fiducials_ct) - 1) * 2 * 0.05


def test_too_few_balls_or_off_tests_nothing():
    """Fewer than MIN_BALLS balls, or a quantile of 0: no floor at all (the others cannot judge
    a ball with 4 or fewer balls in all)."""
    r, J, *_ = fitted(1, 0.15, (0, (3.0, 0.0)))
    k = MIN_BALLS - 1
    assert not disagreement_cover(r[:2 * k], J[:2 * k], np.full(2 * k, 0.01), 0.99)[0].any()
    assert disagreement_cover(r, J, np.full(len(r), 0.01), 0.0)[1] == []
    assert disagreement_cover(r, J, np.full(len(r), 0.01), 0.99)[0].any()
