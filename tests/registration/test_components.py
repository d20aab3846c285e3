"""Building blocks against independent truth: P3P, KD order, sphere-bias model, prior path,
paper method, accuracy report."""

import cv2
import numpy as np
import pytest

from monotracker.geometry import rotation_about_axis
from monotracker.registration import register
from monotracker.registration.kdtree_order import kd_order
from monotracker.registration.p3p import p3p_batch
from monotracker.registration.projection import project_normalised, undistort_to_normalised
from monotracker.registration.report import tre_mm
from monotracker.sim.scenes import ellipse_centre_normalised, make_scene


def test_p3p_recovers_random_poses():
    rng = np.random.default_rng(0)
    H = 300
    X = rng.normal(size=(H, 3, 3)) * 50
    R = np.array([rotation_about_axis(rng.normal(size=3), rng.uniform(0, 3)) for _ in range(H)])
    t = np.c_[rng.normal(size=(H, 2)) * 50, rng.uniform(400, 700, H)]
    P = np.einsum("hij,hkj->hki", R, X) + t[:, None]
    f = P / np.linalg.norm(P, axis=2, keepdims=True)
    Rs, ts, src = p3p_batch(f, X)
    found = np.zeros(H, bool)
    for k, h in enumerate(src):
        if np.abs(Rs[k] - R[h]).max() < 1e-6 and np.abs(ts[k] - t[h]).max() < 1e-4:
            found[h] = True
    assert found.all()
    # every returned solution reprojects the triplet exactly (no spurious roots)
    Pk = np.einsum("sij,skj->ski", Rs, X[src]) + ts[:, None]
    fk = Pk / np.linalg.norm(Pk, axis=2, keepdims=True)
    assert np.abs(fk - f[src]).max() < 1e-6  # < 0.001 px at f = 1100


def test_p3p_agrees_with_opencv():
    rng = np.random.default_rng(1)
    X = rng.normal(size=(3, 3)) * 40
    R = rotation_about_axis([0.3, 1, 0.2], 0.7)
    Pc = X @ R.T + [10, -20, 550]
    xn = Pc[:, :2] / Pc[:, 2:]
    _, rvecs, tvecs = cv2.solveP3P(X, xn.reshape(-1, 1, 2), np.eye(3), None, flags=cv2.SOLVEPNP_P3P)
    f = Pc / np.linalg.norm(Pc, axis=1, keepdims=True)
    Rs, ts, _ = p3p_batch(f[None], X[None])
    ours = sorted(np.round(ts[:, 2], 4).tolist())
    theirs = sorted(np.round([tv.ravel()[2] for tv in tvecs], 4).tolist())
    assert np.allclose(ours, theirs, atol=1e-3)


def test_kd_order_small_example():
    # x-sorted median is point 2; left {0, 1} split on y -> 0 then 1; right {3, 4} on y -> 4 then 3
    P = np.array([[0, 0], [1, 5], [2, 1], [3, 3], [4, 2.0]])
    assert kd_order(P).tolist() == [2, 0, 1, 4, 3]
    batch = np.stack([P, P[::-1]])
    out = kd_order(batch)
    assert out[0].tolist() == [2, 0, 1, 4, 3]
    assert (4 - out[1]).tolist() == [2, 0, 1, 4, 3]


def test_ellipse_centre_model_matches_conic():
    rng = np.random.default_rng(2)
    C = np.c_[rng.uniform(-200, 200, (20, 2)), rng.uniform(300, 800, 20)]
    assert np.allclose(project_normalised(C, 4.0), ellipse_centre_normalised(C, 4.0), atol=1e-12)
    assert not np.allclose(project_normalised(C, None), ellipse_centre_normalised(C, 4.0), atol=1e-7)


def test_undistort_inverts_distortion():
    s = make_scene(np.random.default_rng(3), noise_px=0.0)
    xn = undistort_to_normalised(s.image_points, s.K, s.dist)
    Xc = s.fiducials_ct @ s.T_cam_ct[:3, :3].T + s.T_cam_ct[:3, 3]
    true = Xc[:, :2] / Xc[:, 2:]
    for i, j in s.truth_pairs:
        assert np.linalg.norm(xn[i] - true[j]) * 1100 < 1e-3


def test_sphere_bias_correction_removes_bias():
    """Noise-free ellipse centres: with radius_mm the pose is exact, without it is biased."""
    errs_on, errs_off = [], []
    for seed in range(4):
        s = make_scene(np.random.default_rng(40 + seed), noise_px=0.0, ellipse_bias=True, distance_mm=(400, 450))
        on = register(s.fiducials_ct, s.image_points, s.K, s.dist, radius_mm=s.radius_mm)
        off = register(s.fiducials_ct, s.image_points, s.K, s.dist)
        assert on.ok and off.ok
        errs_on.append(tre_mm(on.T_cam_ct, s.T_cam_ct, s.targets_ct).max())
        errs_off.append(tre_mm(off.T_cam_ct, s.T_cam_ct, s.targets_ct).max())
        assert on.reprojection_rms_px < 1e-4
    assert max(errs_on) < 1e-3
    assert max(errs_off) > 20 * max(errs_on)


def test_prior_path_tracks_small_motion_and_falls_back():
    s = make_scene(np.random.default_rng(8), n_occluded=1, n_stray=1)
    first = register(s.fiducials_ct, s.image_points, s.K, s.dist)
    assert first.ok and not first.used_prior
    # small motion: perturb the true pose by 1 deg / 3 mm and use it as the prior
    P = s.T_cam_ct.copy()
    P[:3, :3] = rotation_about_axis([1, 0.5, 0], np.radians(1.0)) @ P[:3, :3]
    P[:3, 3] += [3, -2, 4]
    r = register(s.fiducials_ct, s.image_points, s.K, s.dist, prior=P)
    assert r.ok and r.used_prior
    assert sorted(r.pairs) == sorted(s.truth_pairs)
    # a far-off prior does not explain the image: full search takes over and is still right
    Q = s.T_cam_ct.copy()
    Q[:3, :3] = rotation_about_axis([0, 0, 1], np.radians(40)) @ Q[:3, :3]
    r2 = register(s.fiducials_ct, s.image_points, s.K, s.dist, prior=Q)
    assert r2.ok and not r2.used_prior and "prior_rejected" in r2.stats
    assert sorted(r2.pairs) == sorted(s.truth_pairs)


def test_paper_method_clean_and_refuses_mismatch():
    right = 0
    for seed in range(5):
        s = make_scene(np.random.default_rng(60 + seed), fiducial_ids=range(5))
        r = register(s.fiducials_ct, s.image_points, s.K, s.dist, method="paper")
        if r.ok:
            assert sorted(r.pairs) == sorted(s.truth_pairs)  # never a wrong pose with ok=True
            right += 1
    assert right >= 3
    s = make_scene(np.random.default_rng(70), n_stray=1)
    r = register(s.fiducials_ct, s.image_points, s.K, s.dist, method="paper")
    assert not r.ok and "exactly one image point" in r.reason


def test_report_fields_and_predicted_tre_is_calibrated():
    """Predicted TRE agrees with the spread of TRE over noise draws (same scene, new noise)."""
    rng = np.random.default_rng(9)
    base = make_scene(rng, noise_px=0.0, distortion=False)
    trues = {i: j for i, j in base.truth_pairs}
    target = base.targets_ct[0]
    errs, preds = [], []
    for _k in range(40):
        pts = base.image_points + rng.normal(scale=1.0, size=base.image_points.shape)
        r = register(base.fiducials_ct, pts, base.K, None)
        assert r.ok and all(trues[i] == j for i, j in r.pairs)
        errs.append(tre_mm(r.T_cam_ct, base.T_cam_ct, target[None])[0])
        preds.append(r.predicted_tre_mm(target))
        assert 0 <= r.fre_mm < 2.0
        assert np.isclose(r.reprojection_rms_px, np.sqrt(np.mean(r.residuals_px**2)))
    rms_err = np.sqrt(np.mean(np.square(errs)))
    assert 0.6 < np.median(preds) / rms_err < 1.6


@pytest.mark.parametrize("method", ["robust", "paper"])
def test_residuals_follow_pair_order(method):
    """residuals_px[k] belongs to pairs[k]: recompute each from the pose independently."""
    from monotracker.registration.projection import project_pixels

    s = make_scene(np.random.default_rng(11), noise_px=0.5, distortion=False, fiducial_ids=range(5))
    r = register(s.fiducials_ct, s.image_points, s.K, None, method=method)
    assert r.ok
    Xc = s.fiducials_ct @ r.T_cam_ct[:3, :3].T + r.T_cam_ct[:3, 3]
    pred = project_pixels(Xc, s.K)
    for k, (i, j) in enumerate(r.pairs):
        assert abs(np.linalg.norm(s.image_points[i] - pred[j]) - r.residuals_px[k]) < 1e-6


def test_quartic_roots_match_numpy():
    from monotracker.registration.quartic import quartic_roots

    rng = np.random.default_rng(12)
    co = rng.normal(size=(5, 300))
    ours = quartic_roots(*co)
    for k in range(co.shape[1]):
        ref = np.roots(co[:, k])
        # same multiset: every reference root is matched and vice versa
        assert max(np.min(np.abs(ours[k] - x)) for x in ref) < 1e-8
        assert max(np.min(np.abs(ref - x)) for x in ours[k]) < 1e-8
