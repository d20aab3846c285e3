"""Robust registration against synthetic ground truth (monotracker.sim.scenes)."""

import numpy as np
import pytest

from monotracker.registration import Registration, register
from monotracker.registration.report import tre_mm
from monotracker.sim.scenes import make_scene


def _check(scene, reg: Registration, tre_max_mm=3.0):
    assert reg.ok, reg.reason
    assert sorted(reg.pairs) == sorted(scene.truth_pairs)
    assert sorted(reg.unmatched_image_indices) == sorted(scene.stray_indices)
    assert tre_mm(reg.T_cam_ct, scene.T_cam_ct, scene.targets_ct).max() < tre_max_mm


@pytest.mark.parametrize("seed", range(6))
def test_clean_phantom(seed):
    s = make_scene(np.random.default_rng(seed))
    r = register(s.fiducials_ct, s.image_points, s.K, s.dist)
    _check(s, r)
    assert r.reprojection_rms_px < 1.0
    assert len(r.residuals_px) == len(r.pairs) == 9


@pytest.mark.parametrize("seed", range(8))
def test_occlusion_and_strays(seed):
    s = make_scene(np.random.default_rng(100 + seed), n_occluded=2, n_stray=2)
    r = register(s.fiducials_ct, s.image_points, s.K, s.dist)
    _check(s, r)


@pytest.mark.parametrize("seed", range(4))
def test_random_layouts(seed):
    s = make_scene(np.random.default_rng(200 + seed), layout="random", n_occluded=1, n_stray=1)
    r = register(s.fiducials_ct, s.image_points, s.K, s.dist)
    _check(s, r)


@pytest.mark.parametrize("cfg", [dict(n_occluded=5), dict(n_occluded=4, n_stray=2, noise_px=1.0),
                                 dict(fiducial_ids=range(5), noise_px=1.0)])
def test_few_fiducials_right_or_refused(cfg):
    """Down to 4 seen: each result is either entirely right or refused with a reason."""
    right = 0
    for seed in range(8):
        s = make_scene(np.random.default_rng(300 + seed), **cfg)
        r = register(s.fiducials_ct, s.image_points, s.K, s.dist)
        if r.ok:
            assert sorted(r.pairs) == sorted(s.truth_pairs)
            right += 1
        else:
            assert r.reason and r.T_cam_ct is None
    assert right >= 3


def test_predicted_tre_and_fre_are_reported():
    s = make_scene(np.random.default_rng(400))
    r = register(s.fiducials_ct, s.image_points, s.K, s.dist)
    p = r.predicted_tre_mm(s.targets_ct)
    assert p.shape == (len(s.targets_ct),) and np.all(p > 0) and np.all(p < 10)
    assert np.isfinite(r.fre_mm) and r.fre_mm >= 0
    assert r.timing["total_s"] > 0 and r.method == "robust"
