import numpy as np
import pytest

from monotracker.errors import MonoTrackerError
from monotracker.geometry import invert_transform
from monotracker.robot import kinematics as kin
from monotracker.robot.lie import adjoint, exp6, log6


@pytest.fixture(scope="module")
def qs():
    return np.random.default_rng(1).uniform(-np.pi, np.pi, (50, 6))


def test_poe_fk_matches_pinocchio(qs):
    for q in qs:
        assert np.abs(kin.poe_fk(q) - kin.fk(q)).max() < 1e-9


def test_poe_jacobians_match_pinocchio(qs):
    for q in qs:
        assert np.abs(kin.poe_jacobian_space(q) - kin.jacobian_space(q)).max() < 1e-9
        assert np.abs(kin.poe_jacobian_body(q) - kin.jacobian_body(q)).max() < 1e-9


def test_body_jacobian_matches_finite_difference(qs):
    q = qs[0]
    T = kin.fk(q)
    J = kin.jacobian_body(q)
    h = 1e-6
    for i in range(6):
        dq = np.zeros(6)
        dq[i] = h
        num = log6(invert_transform(T) @ kin.fk(q + dq)) / h
        assert np.allclose(num, J[:, i], atol=1e-5)


def test_exp_log_roundtrip():
    rng = np.random.default_rng(2)
    for _ in range(100):
        xi = rng.normal(size=6) * np.array([1, 1, 1, 0.5, 0.5, 0.5])
        if np.linalg.norm(xi[:3]) > 3.0:
            continue
        assert np.allclose(log6(exp6(xi)), xi, atol=1e-9)
    # near pi
    xi = np.array([np.pi - 1e-6, 0, 0, 0.1, 0.2, 0.3])
    assert np.allclose(exp6(log6(exp6(xi))), exp6(xi), atol=1e-9)


def test_adjoint_maps_twists():
    rng = np.random.default_rng(3)
    T = exp6(rng.normal(size=6))
    xi_b = rng.normal(size=6)
    # [Ad_T xi] = T [xi] T^-1
    def mat(x):
        M = np.zeros((4, 4))
        M[:3, :3] = np.array([[0, -x[2], x[1]], [x[2], 0, -x[0]], [-x[1], x[0], 0]])
        M[:3, 3] = x[3:]
        return M
    assert np.allclose(mat(adjoint(T) @ xi_b), T @ mat(xi_b) @ invert_transform(T), atol=1e-12)


def test_ik_reaches_tip_target_and_reports_unreachable():
    tool = kin.NeedleTool()
    T_goal = kin.fk(kin.Q_READY + np.array([0.2, -0.1, 0.15, 0.1, -0.2, 0.3])) @ tool.T_tool0_tip
    r = kin.ik(T_goal, kin.Q_READY, T_tool0_tool=tool.T_tool0_tip)
    assert r.ok, r.reason
    assert np.allclose(kin.fk(r.q) @ tool.T_tool0_tip, T_goal, atol=1e-5)
    far = np.eye(4)
    far[:3, 3] = [3.0, 0, 0]  # UR10 reach is ~1.3 m
    bad = kin.ik(far, kin.Q_READY)
    assert not bad.ok and "unreachable" in bad.reason


def test_needle_tool_and_urdf():
    assert kin.urdf_path().name == "ur10_robot.urdf"
    t = kin.NeedleTool(length_m=0.25)
    assert t.T_tool0_tip[2, 3] == pytest.approx(0.25)
    assert t.T_tool0_mid[2, 3] == pytest.approx(0.125)
    with pytest.raises(MonoTrackerError, match="needle length"):
        kin.NeedleTool(length_m=-1)
    # the ready pose: tool pointing down, ~0.5-0.7 m from the base
    T = kin.fk(kin.Q_READY) @ t.T_tool0_tip
    assert T[2, 2] < -0.99
    assert 0.5 < np.linalg.norm(T[:3, 3]) < 0.8


def test_fast_lie_maps_equal_reference():
    from monotracker.geometry import invert_transform as inv_ref
    from monotracker.robot.lie import adjoint_ref, exp6_ref, inverse, log6_ref, relative

    rng = np.random.default_rng(4)
    for _ in range(50):
        xi = rng.normal(size=6)
        T = exp6_ref(xi)
        assert np.allclose(exp6(xi), T, atol=1e-12)
        assert np.allclose(log6(T), log6_ref(T), atol=1e-9)
        assert np.allclose(adjoint(T), adjoint_ref(T), atol=1e-12)
        assert np.allclose(inverse(T), inv_ref(T), atol=1e-12)
        T2 = exp6_ref(rng.normal(size=6))
        assert np.allclose(relative(T, T2), inv_ref(T) @ T2, atol=1e-12)
