"""The compiled pose refinement (registration/pnp_kernels.py) against its NumPy reference
(registration/pnp.py's ``*_reference``): same pose, residuals, normal matrix, Jacobian and
iteration count, on random constellations, noisy observations, point weights, the plain pinhole
and a degenerate (singular) case."""

import numpy as np
import pytest

from monotracker.registration.pnp import (_residuals_and_jacobian, refine_pose, refine_pose_reference,
                                          residuals_and_jacobian_reference, so3_exp)
from monotracker.registration.projection import project_normalised


def _scene(rng, k=9, radius=4.0, noise_px=0.2):
    X = rng.uniform(-60, 60, (k, 3))
    R = so3_exp(rng.normal(scale=0.6, size=3))
    t = np.array([rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(350, 700)])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    fxy = np.array([1100.0, 1105.0])
    obs = project_normalised(X @ R.T + t, radius) + rng.normal(scale=noise_px, size=(k, 2)) / fxy
    # start a few degrees and mm off
    T0 = T.copy()
    T0[:3, :3] = so3_exp(rng.normal(scale=0.03, size=3)) @ R
    T0[:3, 3] += rng.normal(scale=3.0, size=3)
    return T0, X, obs, fxy


@pytest.mark.parametrize("radius", [4.0, None])
@pytest.mark.parametrize("weighted", [False, True])
def test_compiled_refinement_equals_the_numpy_reference(radius, weighted):
    rng = np.random.default_rng(7)
    for _ in range(40):
        k = int(rng.integers(4, 12))
        T0, X, obs, fxy = _scene(rng, k=k, radius=radius or 0.0)
        w = rng.uniform(1, 8, k) if weighted else None
        for max_iter in (20, 3):
            a = refine_pose(T0, X, obs, fxy, radius, max_iter=max_iter, weights=w)
            b = refine_pose_reference(T0, X, obs, fxy, radius, max_iter=max_iter, weights=w)
            # rounding only (BLAS vs scalar sums): well under a micrometre and a micro-pixel
            assert np.allclose(a.T[:3, :3], b.T[:3, :3], rtol=0, atol=1e-8)
            assert np.allclose(a.T[:3, 3], b.T[:3, 3], rtol=0, atol=1e-5)
            assert np.allclose(a.residuals, b.residuals, rtol=0, atol=1e-5)
            assert np.allclose(a.J, b.J, rtol=1e-6, atol=1e-6)
            assert np.allclose(a.JtJ, b.JtJ, rtol=1e-6, atol=1e-3)
            assert a.iterations == b.iterations and a.converged == b.converged


def test_compiled_residuals_and_jacobian_equal_the_reference_and_finite_differences():
    rng = np.random.default_rng(3)
    T0, X, obs, fxy = _scene(rng)
    R, t = T0[:3, :3], T0[:3, 3]
    r, J = _residuals_and_jacobian(R, t, X, obs, fxy, 4.0)
    r2, J2 = residuals_and_jacobian_reference(R, t, X, obs, fxy, 4.0)
    assert np.allclose(r, r2, atol=1e-9) and np.allclose(J, J2, rtol=1e-10, atol=1e-9)
    # independent truth: the Jacobian is the derivative of the residuals (central differences)
    h = 1e-6
    for c in range(6):
        d = np.zeros(6)
        d[c] = h
        rp, _ = residuals_and_jacobian_reference(so3_exp(d[:3]) @ R, t + d[3:], X, obs, fxy, 4.0)
        rm, _ = residuals_and_jacobian_reference(so3_exp(-d[:3]) @ R, t - d[3:], X, obs, fxy, 4.0)
        assert np.allclose((rp - rm) / (2 * h), J[:, c], rtol=1e-5, atol=1e-4)


def test_compiled_refinement_of_a_degenerate_constellation_behaves_like_the_reference():
    # all points on one line: the normal matrix is singular; both give up the same way
    X = np.stack([np.linspace(-40, 40, 5), np.zeros(5), np.zeros(5)], 1)
    T0 = np.eye(4)
    T0[2, 3] = 500.0
    obs = project_normalised(X + T0[:3, 3], 4.0)
    fxy = np.array([1000.0, 1000.0])
    a = refine_pose(T0, X, obs, fxy, 4.0)
    b = refine_pose_reference(T0, X, obs, fxy, 4.0)
    assert np.allclose(a.T, b.T, atol=1e-6) and a.converged == b.converged
