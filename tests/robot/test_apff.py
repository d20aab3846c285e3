"""APFF pieces against analytic values and the paper's written-out formulas."""

import numpy as np
import pytest

from monotracker.robot import kinematics as kin
from monotracker.robot.apff import (APFFController, APFFParams, attractive_force, dls_solve,
                                    point_wrench_space, repulsive_force)
from monotracker.robot.head import Corridor, HeadSphere, fit_head_sphere
from monotracker.robot.lie import adjoint_ref, exp6_ref
from monotracker.sim.phantom import default_phantom


def test_attractive_force_quadratic_then_conical():
    g = np.zeros(3)
    assert np.allclose(attractive_force(np.array([0.01, 0, 0]), g, 100.0, 0.02), [-1.0, 0, 0])
    far = attractive_force(np.array([0.0, 0.3, 0.4]), g, 100.0, 0.02)
    assert np.linalg.norm(far) == pytest.approx(2.0)  # zeta * d
    assert np.allclose(far / 2.0, [0, -0.6, -0.8])
    # continuous at d
    a = attractive_force(np.array([0.02, 0, 0]), g, 100.0, 0.02)
    b = attractive_force(np.array([0.020001, 0, 0]), g, 100.0, 0.02)
    assert np.allclose(a, b, atol=1e-4)


def test_repulsive_force_khatib():
    head = HeadSphere(np.zeros(3), 0.1)
    eta, rho0 = 1e-5, 0.03
    p = np.array([0.0, 0.0, 0.11])  # rho = 0.01
    f = repulsive_force(p, head, eta, rho0)
    assert np.allclose(f, [0, 0, eta * (1 / 0.01 - 1 / 0.03) / 0.01**2])
    assert np.allclose(repulsive_force(np.array([0.0, 0.0, 0.2]), head, eta, rho0), 0)
    # pushes outwards from inside too (floored at 1 mm)
    assert repulsive_force(np.array([0.05, 0, 0]), head, eta, rho0)[0] > 0


def test_body_wrench_equals_paper_eq_19_21():
    c = APFFController()
    c.head = HeadSphere(np.array([0.5, 0.2, 0.2]), 0.09)
    rng = np.random.default_rng(0)
    T_mid = exp6_ref(rng.normal(size=6) * 0.3)
    T_goal = exp6_ref(rng.normal(size=6) * 0.3)
    T_target = T_goal @ c._T_mid_tip
    F = c.apf_wrench_body(T_mid, T_goal, T_target)
    # written out: forces at P_top and P_rem in the base frame, (r x f; f), Ad^T to the body
    h = c.tool.length_m / 2
    F_s = np.zeros(6)
    for s in (1, -1):
        r = T_mid[:3, 3] + s * h * T_mid[:3, 2]
        g = T_goal[:3, 3] + s * h * T_goal[:3, 2]
        f = attractive_force(r, g, c.p.zeta, c.p.d)
        if not Corridor().contains(r[None], T_target)[0]:
            f = f + repulsive_force(r, c.head, c.p.eta, c.p.rho0)
        F_s += point_wrench_space(r, f)
    assert np.allclose(F, adjoint_ref(T_mid).T @ F_s, atol=1e-12)


def test_near_stage_dynamics_match_second_order_model():
    """Paper Eq. 27-28: near the target APF-A-II is M S'' + B S' + K2 S = 0 per axis."""
    c = APFFController("APF-A-II")
    T_target = kin.fk(kin.Q_READY) @ c.tool.T_tool0_tip
    T_goal = c.target_mid(T_target)
    x0 = 0.002  # 2 mm below the goal along base x: ||S|| < epsilon, so the near stage
    T_mid0 = T_goal.copy()
    T_mid0[0, 3] -= x0
    T_mid_tool0 = np.linalg.inv(c.tool.T_tool0_mid)
    J = kin.jacobian_body(kin.Q_READY)
    dt, n = 1e-4, 2000
    xs = []
    T_mid = T_mid0
    for _ in range(n):
        # an ideal arm: the measured pose is the controller's reference pose
        c.step(T_mid @ T_mid_tool0, J, np.zeros(6), T_target, dt)
        T_mid = c.T_ref
        xs.append(T_goal[0, 3] - T_mid[0, 3])
    assert c.near
    # analytic solution of the translational axis
    m, b, k = c._m[3], c._b[3], c._k2[3]
    wn = np.sqrt(k / m)
    zeta = b / (2 * np.sqrt(m * k))
    t = dt * np.arange(1, n + 1)
    if zeta > 1:
        r1 = -wn * (zeta - np.sqrt(zeta**2 - 1))
        r2 = -wn * (zeta + np.sqrt(zeta**2 - 1))
        A = x0 * r2 / (r2 - r1)
        x = A * np.exp(r1 * t) + (x0 - A) * np.exp(r2 * t)
    else:
        wd = wn * np.sqrt(1 - zeta**2)
        x = x0 * np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta * wn / wd * np.sin(wd * t))
    assert np.abs(np.array(xs) - x).max() < 2e-5


def test_dls_exact_when_regular_and_bounded_at_singularity():
    J = kin.jacobian_body(kin.Q_READY)
    V = np.array([0.1, 0, 0, 0, 0.05, 0])
    x, smin = dls_solve(J, V, 0.05, 0.05)
    assert smin > 0.05 and np.allclose(J @ x, V, atol=1e-12)
    q = kin.Q_READY.copy()
    q[4] = 0.0  # wrist singularity
    Js = kin.jacobian_body(q)
    x, smin = dls_solve(Js, V, 0.05, 0.05)
    assert smin < 1e-9 and np.all(np.isfinite(x)) and np.abs(x).max() < 10.0


def test_bad_params_rejected():
    with pytest.raises(ValueError):
        APFFController("APF-X")
    with pytest.raises(ValueError):
        APFFController(params=APFFParams(M=np.ones((6, 6))))


def test_head_sphere_fit_on_phantom_and_with_outlier():
    ph = default_phantom()
    pts = ph.fiducial_centres_lps
    r = fit_head_sphere(pts)
    assert r.ok, r.reason
    # fiducials lie on a (non-spherical) ellipsoid patch: a head-sized sphere near them
    assert 60 < r.radius_mm < 130
    assert np.abs(np.linalg.norm(pts[r.inliers] - r.centre_mm, axis=1) - r.radius_mm).max() < 3.0
    # exact sphere + one gross outlier
    rng = np.random.default_rng(0)
    d = rng.normal(size=(8, 3))
    d[:, 2] = np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sph = np.array([10.0, -5.0, 30.0]) + 85.0 * d
    sph = np.vstack([sph, [300.0, 0, 0]])
    r = fit_head_sphere(sph)
    assert r.ok and abs(r.radius_mm - 85.0) < 1e-6 and 8 not in r.inliers
    assert np.allclose(r.centre_mm, [10, -5, 30], atol=1e-6)
    assert not fit_head_sphere(sph[:3]).ok
    assert not fit_head_sphere(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]) * 50).ok
    assert not fit_head_sphere(np.full((5, 3), np.nan)).ok
