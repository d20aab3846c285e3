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
