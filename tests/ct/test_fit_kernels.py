"""The compiled sphere fits (ct/fit_kernels.py) against SciPy's least_squares (the reference,
sphere_fit's solver="scipy") and against the true balls they were drawn from."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from monotracker.ct import fit_kernels, sphere_fit
from monotracker.ct.fiducials import detect_fiducials


def _ball(rng, with_plane: bool):
    """Voxel centres (n, 3) mm and noisy values (HU) of a blurred ball on a 0.5 x 0.5 x
    (1 or 2) mm grid, optionally resting on a plane of soft tissue; the true parameters."""
    c = rng.uniform(-1, 1, 3)
    r, s, H, b = rng.uniform(1.5, 5), rng.uniform(0.3, 0.8), rng.uniform(1500, 3000), rng.uniform(-1000, 50)
    sp = np.array([0.5, 0.5, rng.choice([1.0, 2.0])])
    axes = [np.arange(-r - 3, r + 3, sp[a]) for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3) + rng.uniform(0, 0.5, 3)
    M = np.diag(sp**2 / 12.0)
    truth = np.r_[c, r, s, H, b]
    vals = sphere_fit._sphere_model(truth, pts, M)[0] + rng.normal(0, 18, len(pts))
    if with_plane:  # scalp under the ball (a level the one-background model does not have)
        under = (pts[:, 2] < c[2] - r + 0.3) & (np.linalg.norm(pts - c, axis=1) > r)
        vals = np.where(under, 40.0 + rng.normal(0, 18, len(pts)), vals)
    return pts, vals, M, truth


@pytest.mark.parametrize("seed", range(8))
def test_compiled_sphere_fit_agrees_with_scipy_and_truth(seed):
    rng = np.random.default_rng(seed)
    pts, vals, M, truth = _ball(rng, with_plane=seed % 2 == 1)
    x0 = np.r_[truth[:3] + rng.normal(0, 0.4, 3), truth[3] * 1.1, 0.4, truth[5] * 0.9, truth[6] + 50]
    f_scale = max(54.0, 0.03 * (truth[5] - truth[6]))
    ref, rms_ref, ok_ref = sphere_fit.fit_blurred_sphere(pts, vals, x0, f_scale, M, solver="scipy")
    got, rms, ok = sphere_fit.fit_blurred_sphere(pts, vals, x0, f_scale, M, solver="compiled")
    assert ok and ok_ref
    assert np.linalg.norm(got[:3] - ref[:3]) < 1e-3  # mm
    assert abs(got[3] - ref[3]) < 1e-3 and abs(rms - rms_ref) < 0.01 * rms_ref
    if seed % 2 == 0:  # the model is right: the true centre, within noise
        assert np.linalg.norm(got[:3] - truth[:3]) < 0.05


def test_early_stops_reach_the_same_minimum_in_fewer_voxel_evaluations(monkeypatch):
    """The compiled fits' extra stopping tests (``STOP_DECREMENT``, ``STOP_STEP_MM``) against the
    same fits run until SciPy's tests stop them (both off): on random balls (a plane of tissue
    under half of them; plain and on-surface models, subsample and polish), every centre and
    radius within 2e-4 mm (twice the step tolerance), and at least a tenth fewer voxel
    evaluations in all (0.80 of them here; 0.5 on the whole-head phantoms)."""
    from monotracker.ct import fit_kernels

    evals = []
    lm = fit_kernels.robust_lm

    def counting(*a):
        out = lm(*a)
        evals.append(out[3] * len(a[4]))
        return out

    monkeypatch.setattr(fit_kernels, "robust_lm", counting)

    def fits():
        out = []
        for seed in range(10):
            rng = np.random.default_rng(100 + seed)
            pts, vals, M, truth = _ball(rng, with_plane=seed % 2 == 1)
            x0 = np.r_[truth[:3] + rng.normal(0, 0.4, 3), truth[3] * 1.1, 0.4, truth[5] * 0.9, truth[6] + 50]
            f_scale = max(54.0, 0.03 * (truth[5] - truth[6]))
            got, _, ok = sphere_fit.fit_blurred_sphere(pts, vals, x0, f_scale, M)
            out.append((got[:4], ok))
            if seed % 2 == 1:
                surf = sphere_fit.refine_on_surface(pts, vals, got, f_scale, M, psf_given=True)
                if surf is not None:
                    out.append((surf[0][:4], True))
        return out

    early = fits()
    n_early = sum(evals)
    evals.clear()
    monkeypatch.setattr(sphere_fit, "STOP_DECREMENT", 0.0)
    monkeypatch.setattr(sphere_fit, "STOP_STEP_MM", 0.0)
    full = fits()
    n_full = sum(evals)
    assert len(early) == len(full) > 10
    for (a, ok_a), (b, ok_b) in zip(early, full):
        assert ok_a and ok_b
        assert np.abs(a - b).max() < 2e-4  # centre and radius, mm
    assert n_early < 0.9 * n_full


def test_compiled_fit_holds_a_parameter_at_its_bound():
    """A radius bound below the true radius: both solvers stop on the bound (projected step)."""
    rng = np.random.default_rng(3)
    pts, vals, M, truth = _ball(rng, with_plane=False)
    x0 = np.r_[truth[:3], 0.8 * truth[3], 0.4, truth[5], truth[6]]
    bounds = (0.5 * truth[3], 0.9 * truth[3])
    ref = sphere_fit.fit_blurred_sphere(pts, vals, x0, 60.0, M, r_bounds=bounds, solver="scipy")[0]
    got = sphere_fit.fit_blurred_sphere(pts, vals, x0, 60.0, M, r_bounds=bounds, solver="compiled")[0]
    assert abs(got[3] - bounds[1]) < 1e-3 and abs(ref[3] - bounds[1]) < 1e-3
    assert np.linalg.norm(got[:3] - ref[:3]) < 5e-3


def test_detection_with_either_solver_gives_the_same_balls(monkeypatch):
    """The metal scan of the CT tests (1500 HU balls beside fillings and a rod): the same
    fiducials, centres within 1e-3 mm of each other and within 0.1 mm of the truth."""
    from ct_test_helpers import patch_params

    from monotracker.ct.volume import Volume
    from monotracker.sim.ct_phantom import generate_ct, metal_distractors
    from monotracker.sim.phantom import default_phantom

    ph = default_phantom()
    ct = generate_ct(ph, patch_params(ph, spacing_mm=(0.8, 0.8, 1.25), fiducial_hu=1500.0,
                                      distractors=metal_distractors(ph, streak_hu=300.0)))
    vol = Volume.from_image(ct.to_sitk())
    monkeypatch.setattr(sphere_fit, "SOLVER", "scipy")
    ref = detect_fiducials(vol)
    monkeypatch.setattr(sphere_fit, "SOLVER", "compiled")
    got = detect_fiducials(vol)
    assert len(got.centres) == len(ref.centres) == len(ct.fiducial_centres_lps)
    D = cdist(got.centres, ref.centres)
    assert D.min(axis=1).max() < 1e-3
    assert cdist(got.centres, ct.fiducial_centres_lps).min(axis=1).max() < 0.1


_WARM_SCRIPT = """
import numpy as np
from monotracker.ct import fit_kernels, label_kernels, sphere_fit
from monotracker.ct.fiducials import detect_fiducials
from monotracker.ct.volume import Volume
from monotracker.sim.ct_phantom import generate_ct, patch_scan_params
from monotracker.sim.phantom import default_phantom

kernels = (label_kernels._label_runs, label_kernels._listed_above, label_kernels._label_stats, label_kernels._add_run, fit_kernels.fit_window)
assert not fit_kernels.robust_lm.signatures and not any(k.signatures for k in kernels)
sphere_fit.warm_up()
warm = set(fit_kernels.robust_lm.signatures)
warm_labels = [set(k.signatures) for k in kernels]
ct = generate_ct(default_phantom(), patch_scan_params(None, 7.0))
det = detect_fiducials(Volume.from_image(ct.to_sitk()))
assert det.ok, det.reason
assert all(not set(k.signatures) - w for k, w in zip(kernels, warm_labels)), "the blob search or a fit window compiled a new signature"
print(len(warm), len(set(fit_kernels.robust_lm.signatures) - warm))
"""


def test_warm_up_compiles_what_a_detection_runs(tmp_path):
    """After :func:`sphere_fit.warm_up` a detection compiles nothing more: the warm-up passes
    the fits the same argument types (a fresh process). The process uses numba's disk cache as
    the app does: a kernel's ``signatures`` lists every signature the process compiled or loaded
    from the cache, so a type the warm-up misses shows up either way; an empty cache folder only
    made this test compile every kernel from scratch (~30 s of the suite, issue 35)."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _WARM_SCRIPT], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    n_warm, n_new = (int(x) for x in out.stdout.split()[-2:])
    assert n_warm >= 1 and n_new == 0


def test_loading_a_ct_starts_the_warm_up(tmp_path):
    """Loading a CT starts the fits' compilation on a background thread (once per process)."""
    import SimpleITK as sitk

    from monotracker.ct.volume import load_volume

    img = sitk.GetImageFromArray(np.full((8, 8, 8), 40, np.int16))
    sitk.WriteImage(img, str(tmp_path / "ct.nii.gz"))
    try:
        load_volume(tmp_path / "ct.nii.gz")
    except Exception:  # noqa: BLE001 - the volume may be refused as not a head CT; the thread started before
        pass
    t = sphere_fit._warm_thread
    assert t is not None and t.name == "ct-fit-warm-up"
    t.join()
    assert sphere_fit.warm_up_in_background() is t


def test_fit_window_matches_numpy():
    """The compiled fit window (one pass over the box) keeps the voxels the array code of
    before kept: within the blurred reach of the centre, nearer to this blob than to each
    neighbour, positions from the grid's own affine (an oblique, sheared one here), C order;
    and lists every padding voxel of the box."""
    rng = np.random.default_rng(5)
    D = np.linalg.qr(rng.normal(size=(3, 3)))[0] @ np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    sp = np.array([0.45, 0.6, 1.3])
    A, origin = D * sp[None, :], np.array([-20.0, 7.0, 3.0])
    vol = rng.integers(-1024, 2000, size=(30, 40, 36)).astype(np.int16)
    vol[3:6, 4:9, 2:5] = -1024
    lo, hi = np.array([2, 3, 1]), np.array([22, 31, 30])
    sub = vol[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    kji = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 3)
    pts = kji[:, ::-1].astype(float) @ A.T + origin
    vals = sub.astype(float).ravel()
    centre = pts[len(pts) // 2] + 0.3
    r0 = 3.0
    M = (D * (sp**2 / 12.0)) @ D.T
    sib_c, sib_r = np.array([centre + [4.0, 0.5, -1.0], centre + [-2.0, 5.0, 0.0]]), np.array([2.0, 1.5])
    rel = pts - centre
    dist = np.linalg.norm(rel, axis=1)
    e = rel / np.maximum(dist, 1e-9)[:, None]
    near = dist < r0 + 1.5 + 2.5 * np.sqrt(0.25 + np.einsum("ij,jk,ik->i", e, M, e))
    for c, r in zip(sib_c, sib_r):
        near &= np.linalg.norm(pts - c, axis=1) - r > dist - r0
    got_pts, got_vals, got_dist, got_pad = fit_kernels.fit_window(sub, lo.astype(np.int64), A, origin, centre, r0, M,
                                                                  sib_c, sib_r, -1024.0, True)
    assert 100 < near.sum() < len(near) and len(got_pts) == near.sum()
    np.testing.assert_allclose(got_pts, pts[near], atol=1e-9)
    np.testing.assert_array_equal(got_vals, vals[near])
    np.testing.assert_allclose(got_dist, dist[near], atol=1e-9)
    np.testing.assert_allclose(got_pad, pts[vals == -1024.0], atol=1e-9)
    assert len(got_pad) >= 45  # the padded block (3 x 5 x 3), and random -1024s
    none = fit_kernels.fit_window(sub, lo.astype(np.int64), A, origin, centre, r0, M, np.zeros((0, 3)), np.zeros(0), 0.0, False)
    assert len(none[3]) == 0 and len(none[0]) > len(got_pts)
