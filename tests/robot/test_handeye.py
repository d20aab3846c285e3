import json

import numpy as np
import pytest

from monotracker.errors import InputError
from monotracker.geometry import invert_transform, rotation_angle_deg
from monotracker.robot.handeye import (calibrate_eye_to_hand, load_handeye, save_handeye,
                                       simulate_calibration)


def test_noise_free_calibration_recovers_truth_exactly():
    sim = simulate_calibration(10, pixel_noise=0.0, seed=1)
    # exact observations from the truth (no PnP error at all)
    T_ct = [invert_transform(sim.T_base_cam_mm) @ a @ sim.T_tool0_target_mm for a in sim.T_base_tool0_mm]
    r = calibrate_eye_to_hand(sim.T_base_tool0_mm, T_ct)
    assert r.ok, r.reason
    assert np.allclose(r.T_base_cam_mm, sim.T_base_cam_mm, atol=1e-6)
    assert np.allclose(r.T_tool0_target_mm, sim.T_tool0_target_mm, atol=1e-6)
    assert r.translation_rms_mm < 1e-6


def test_simulated_run_with_pixel_noise_is_within_a_few_mm(tmp_path):
    sim = simulate_calibration(15, pixel_noise=0.2, seed=0)
    assert len(sim.T_base_tool0_mm) == 15
    r = calibrate_eye_to_hand(sim.T_base_tool0_mm, sim.T_cam_target_mm)
    assert r.ok
    assert np.linalg.norm(r.T_base_cam_mm[:3, 3] - sim.T_base_cam_mm[:3, 3]) < 3.0
    assert rotation_angle_deg(r.T_base_cam_mm[:3, :3], sim.T_base_cam_mm[:3, :3]) < 0.3
    assert 0 < r.translation_rms_mm < 3.0 and r.rotation_residuals_deg.shape == (15,)
    path = save_handeye(r, tmp_path / "he.json")
    assert np.allclose(load_handeye(path), r.T_base_cam_mm)
    data = json.loads(path.read_text())
    assert data["units"] == "mm" and data["n_poses"] == 15


def test_degenerate_and_bad_inputs():
    sim = simulate_calibration(6, seed=2)
    # pure translations: not enough rotation
    T = [np.eye(4) for _ in range(5)]
    for i, t in enumerate(T):
        t[:3, 3] = [i * 10.0, 0, 0]
    r = calibrate_eye_to_hand(T, T)
    assert not r.ok and "rotate" in r.reason
    assert not calibrate_eye_to_hand(sim.T_base_tool0_mm[:2], sim.T_cam_target_mm[:2]).ok
    with pytest.raises(InputError):
        calibrate_eye_to_hand(sim.T_base_tool0_mm, sim.T_cam_target_mm[:-1])
    bad = list(sim.T_cam_target_mm)
    bad[0] = np.full((4, 4), np.nan)
    with pytest.raises(InputError):
        calibrate_eye_to_hand(sim.T_base_tool0_mm, bad)


def test_load_errors_are_one_line(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_handeye(tmp_path / "nope.json")
    p = tmp_path / "x.json"
    p.write_text("{garbage")
    with pytest.raises(InputError, match="not a MonoTracker calibration"):
        load_handeye(p)
