"""The compiled sphere fits (ct/fit_kernels.py) against SciPy's least_squares (the reference,
sphere_fit's solver="scipy") and against the true balls they were drawn from."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from monotracker.ct import sphere_fit
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
