"""Trust on shaded images (issue 28 item 3): the parts of the predicted TRE that cover a centre
bias, each against an independent truth (Monte Carlo refits, sampling distributions)."""

from __future__ import annotations

import numpy as np

from monotracker.registration.noise import pooled_sigma
from monotracker.registration.pnp import refine_pose, so3_exp
from monotracker.registration.report import (common_shift_covariance, layout_gradient_covariance, layout_units,
                                             target_covariance, tre_mm)

FXY = np.array([1000.0, 1000.0])


def _scene(k: int = 6, seed: int = 1):
    """A pose 450 mm away, k balls spread over a 90 mm patch, a target 80 mm deep."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-45, 45, (k, 2)), rng.uniform(-8, 8, k)]
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.3, -0.2, 0.1]))
    T[:3, 3] = [10.0, -5.0, 450.0]
    target = np.array([0.0, 0.0, -80.0])
    Xc = X @ T[:3, :3].T + T[:3, 3]
    obs = Xc[:, :2] / Xc[:, 2:]
    return X, T, obs, target


def test_a_shift_common_to_all_balls_moves_the_pose_as_predicted():
    """Every ball's centre shifted by the same random vector (0.3 px per coordinate): the
    spread of the refitted poses' error at the target is what ``common_shift_covariance``
    predicts, and the residuals of those fits stay near zero (they cannot show it)."""
    X, T, obs, target = _scene()
    sigma = 0.3
    fit0 = refine_pose(T, X, obs, FXY)
    cov3 = target_covariance(T, common_shift_covariance(fit0.J, sigma), target)
    predicted_rms = float(np.sqrt(np.trace(cov3)))
    rng = np.random.default_rng(7)
    errs, rms_res = [], []
    for _ in range(300):
        shift = rng.normal(0.0, sigma, 2) / FXY
        fit = refine_pose(T, X, obs + shift, FXY)
        errs.append(float(tre_mm(fit.T, T, target)[0]))
        rms_res.append(float(np.sqrt(np.mean(fit.residuals**2))))
    actual_rms = float(np.sqrt(np.mean(np.square(errs))))
    assert predicted_rms > 0.05, "a common shift must move the target"
    np.testing.assert_allclose(actual_rms, predicted_rms, rtol=0.12)
    assert np.median(rms_res) < 0.1 * sigma, "the residuals would have shown the shift"


def test_a_bias_changing_linearly_across_the_layout_moves_the_pose_as_predicted():
    """Each ball's centre moved by G u_i (u_i: its position about the balls' centroid over their
    RMS distance; G a random 2x2 matrix, 0.15 px per entry, as on Blender's frames): the spread
    of the refitted poses' error at the target is what ``layout_gradient_covariance`` predicts;
    the residuals show little of it (a pose absorbs most of an affine field)."""
    X, T, obs, target = _scene()
    sigma = 0.15
    fit0 = refine_pose(T, X, obs, FXY)
    px = obs * FXY
    cov3 = target_covariance(T, layout_gradient_covariance(fit0.J, px, sigma), target)
    predicted_rms = float(np.sqrt(np.trace(cov3)))
    u = layout_units(px)
    assert np.allclose(u.mean(axis=0), 0) and np.isclose(np.mean(np.sum(u**2, axis=1)), 1.0)
    rng = np.random.default_rng(8)
    errs, rms_res, rms_field = [], [], []
    for _ in range(300):
        G = rng.normal(0.0, sigma, (2, 2))
        field = u @ G.T
        fit = refine_pose(T, X, obs + field / FXY, FXY)
        errs.append(float(tre_mm(fit.T, T, target)[0]))
        rms_res.append(float(np.sqrt(np.mean(fit.residuals**2))))
        rms_field.append(float(np.sqrt(np.mean(field**2))))
    actual_rms = float(np.sqrt(np.mean(np.square(errs))))
    assert predicted_rms > 0.1, "a gradient must move the target"
    np.testing.assert_allclose(actual_rms, predicted_rms, rtol=0.12)
    assert np.median(rms_res) < 0.5 * np.median(rms_field), "the residuals would have shown the field"
    # a common shift is no gradient: the two covers are different things
    cov_c = target_covariance(T, common_shift_covariance(fit0.J, sigma), target)
    assert abs(np.sqrt(np.trace(cov_c)) - predicted_rms) > 0.1 * predicted_rms


def test_pooled_sigma_covers_the_true_ball_error_and_never_hides_a_larger_one():
    """Per-ball errors of true size s (px per coordinate) in a 6-ball fit (6 dof): the upper
    bound covers s in about 95 % of trials whatever the prior says; with a prior far too small
    the residuals alone count (source "data")."""
    rng = np.random.default_rng(3)
    dof = 6
    for s_true, prior in ((0.2, 0.2), (0.6, 0.1), (0.1, 0.3)):
        covered, data = 0, 0
        n = 2000
        for _ in range(n):
            rss = float(np.sum(rng.normal(0.0, s_true, dof) ** 2))
            ps = pooled_sigma(rss, dof, noise_px=0.0, frames_harmonic=8.0, prior_ball_px=prior, prior_dof=6)
            covered += ps.upper_px >= s_true
            data += ps.source == "data"
        if prior >= s_true:
            assert covered / n >= 0.95
        else:
            assert covered / n >= 0.80, (s_true, prior, covered / n)
            assert data / n > 0.5, "a prior far below the residuals must not hide them"
