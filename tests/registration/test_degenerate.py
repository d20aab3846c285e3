"""Bad or degenerate inputs give ok=False with a reason, never a pose or a traceback."""

import numpy as np
import pytest

from monotracker.errors import InputError
from monotracker.registration import register
from monotracker.sim.scenes import make_scene


@pytest.fixture(scope="module")
def scene():
    return make_scene(np.random.default_rng(7))


def _fails(r, word):
    assert not r.ok
    assert r.T_cam_ct is None
    assert word in r.reason.lower(), r.reason


def test_fewer_than_four_image_points(scene):
    _fails(register(scene.fiducials_ct, scene.image_points[:3], scene.K, scene.dist), "need at least 4")


def test_fewer_than_four_fiducials(scene):
    _fails(register(scene.fiducials_ct[:3], scene.image_points, scene.K, scene.dist), "need at least 4")


def test_collinear_fiducials(scene):
    X = np.outer(np.arange(6.0), [10.0, 5.0, 2.0])
    _fails(register(X, scene.image_points, scene.K, scene.dist), "collinear")


def test_coplanar_fiducials(scene):
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-50, 50, (8, 2)), np.zeros(8)]
    _fails(register(X, scene.image_points, scene.K, scene.dist), "coplanar")


def test_all_points_stray(scene):
    rng = np.random.default_rng(3)
    pts = rng.uniform([200, 100], [1000, 600], (9, 2))
    r = register(scene.fiducials_ct, pts, scene.K, scene.dist)
    assert not r.ok and r.reason


def test_nan(scene):
    pts = scene.image_points.copy()
    pts[2, 0] = np.nan
    _fails(register(scene.fiducials_ct, pts, scene.K, scene.dist), "nan")
    X = scene.fiducials_ct.copy()
    X[0, 1] = np.nan
    _fails(register(X, scene.image_points, scene.K, scene.dist), "nan")


def test_duplicate_points(scene):
    pts = scene.image_points.copy()
    pts[3] = pts[1] + 0.2
    _fails(register(scene.fiducials_ct, pts, scene.K, scene.dist), "duplicate")
    X = scene.fiducials_ct.copy()
    X[4] = X[0]
    _fails(register(X, scene.image_points, scene.K, scene.dist), "duplicate")


def test_bad_shapes_and_intrinsics(scene):
    _fails(register(scene.fiducials_ct[:, :2], scene.image_points, scene.K), "(n, 3)")
    _fails(register(scene.fiducials_ct, scene.image_points, np.eye(2)), "3x3")
    _fails(register(scene.fiducials_ct, scene.image_points, scene.K, dist=[1.0, 2.0]), "dist")
    _fails(register(scene.fiducials_ct, scene.image_points, scene.K, radius_mm=-1), "radius")


def test_unknown_method_raises_input_error(scene):
    with pytest.raises(InputError):
        register(scene.fiducials_ct, scene.image_points, scene.K, method="magic")


def test_symmetric_layout_is_ambiguous():
    """A layout with a mirror symmetry seen head-on: two assignments explain the image."""
    from monotracker.registration.projection import project_pixels
    from monotracker.sim.scenes import default_K

    X = np.array([[-40, 0, 0], [40, 0, 0], [0, 30, 12], [0, -30, 12], [0, 0, 25.0]])
    K = default_K()
    T = np.eye(4)
    T[:3, 3] = [0, 0, 500]
    pts = project_pixels(X @ T[:3, :3].T + T[:3, 3], K)
    r = register(X, pts, K)
    _fails(r, "ambiguous")


def test_pose_never_wrong_when_ok_under_heavy_clutter():
    """Many strays and few fiducials: either the right pairs or ok=False, never a wrong pose."""
    wrong = 0
    for seed in range(10):
        s = make_scene(np.random.default_rng(500 + seed), n_occluded=4, n_stray=4, noise_px=0.5)
        r = register(s.fiducials_ct, s.image_points, s.K, s.dist)
        if r.ok and sorted(r.pairs) != sorted(s.truth_pairs):
            wrong += 1
    assert wrong == 0


def test_non_numeric_radius_and_json_summary(scene):
    import json

    _fails(register(scene.fiducials_ct, scene.image_points, scene.K, radius_mm="big"), "radius")
    r = register(scene.fiducials_ct, scene.image_points, scene.K, scene.dist, radius_mm=4.0)
    d = json.loads(json.dumps(r.to_dict()))
    assert d["ok"] and len(d["pairs"]) == 9 and len(d["T_cam_ct"]) == 4


def test_non_numeric_inputs_are_refused_with_the_first_failing_check(scene):
    X, P, K = scene.fiducials_ct, scene.image_points, scene.K
    _fails(register("abc", P, K), "not numeric")
    _fails(register(X, P, K, dist="abc"), "dist is not numeric")
    _fails(register(X, P, K, dist=[0.0, 0.0, 0.0, np.inf]), "finite opencv coefficients")
    # checklist order: the shape of the fiducials is checked before dist and radius
    _fails(register(X[:, :2], P, K, dist="abc", radius_mm=-1), "fiducials_ct must be (n, 3)")
    _fails(register(X, P, K, dist="abc", radius_mm=-1), "dist is not numeric")


@pytest.mark.parametrize("prior", ["junk", np.full((4, 4), np.nan), np.eye(3)])
def test_a_broken_prior_is_ignored_not_raised(scene, prior):
    """A prior that is not a finite 4x4 is dropped: the full search runs and finds the truth."""
    r = register(scene.fiducials_ct, scene.image_points, scene.K, scene.dist, radius_mm=scene.radius_mm, prior=prior)
    assert r.ok, r.reason
    assert not r.used_prior
    assert sorted(r.pairs) == sorted(scene.truth_pairs)
