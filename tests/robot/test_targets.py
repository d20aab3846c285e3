import numpy as np
import pytest

from monotracker.errors import InputError
from monotracker.robot import kinematics as kin
from monotracker.robot.targets import align_roll, needle_pose_from_path, reachable
from monotracker.robot.units import transform_m_to_mm
from monotracker.sim.phantom import default_phantom


def test_needle_pose_from_sample_plan():
    ph = default_phantom()
    T = needle_pose_from_path(ph.sample_entry_lps, ph.sample_target_lps, standoff_mm=10.0)
    d = ph.sample_target_lps - ph.sample_entry_lps
    assert np.allclose(T[:3, 2], d / np.linalg.norm(d))
    assert np.allclose(T[:3, 3], ph.sample_entry_lps - 10.0 * T[:3, 2])
    assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3)) and np.linalg.det(T[:3, :3]) > 0
    with pytest.raises(InputError):
        needle_pose_from_path([0, 0, 0], [0, 0, 0.1])
    with pytest.raises(InputError):
        needle_pose_from_path([0, 0, np.nan], [0, 0, 10])


def test_align_roll_keeps_axis_and_matches_current_x():
    T = needle_pose_from_path([0, 0, 0], [0, 0, -50.0])
    cur = np.eye(4)
    cur[:3, :3] = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1.0]])
    A = align_roll(T, cur)
    assert np.allclose(A[:3, 2], T[:3, 2]) and np.allclose(A[:3, 3], T[:3, 3])
    assert np.allclose(A[:3, 0], [0, 1, 0], atol=1e-12)


def test_reachable_in_mm():
    T = transform_m_to_mm(kin.fk(kin.Q_READY + 0.1) @ kin.NeedleTool().T_tool0_tip)
    r = reachable(T)
    assert r.ok
    far = T.copy()
    far[:3, 3] = [2500.0, 0, 0]
    assert not reachable(far).ok
