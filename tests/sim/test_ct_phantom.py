"""The synthetic CT generator against the analytic phantom it voxelises."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.special import erfc

from monotracker.paths import sample_ct_path
from monotracker.sim.ct_phantom import SAMPLE_PARAMS, ScanParams, default_distractors, generate_ct, with_radius
from monotracker.sim.phantom import HU, default_phantom


@pytest.fixture(scope="module")
def coarse():
    """Whole head, 1.0 x 1.1 x 1.6 mm, oblique, no noise (so levels can be checked exactly)."""
    return generate_ct(default_phantom(), ScanParams(spacing_mm=(1.0, 1.1, 1.6), noise_hu=0.0))


def _lps_grid(ct):
    k, j, i = np.indices(ct.array.shape)
    ijk = np.stack([i, j, k], axis=-1).reshape(-1, 3).astype(float)
    return ijk @ (ct.direction * ct.spacing_mm).T + ct.origin_mm


def test_int16_hu_oblique_anisotropic(coarse):
    assert coarse.array.dtype == np.int16
    assert not np.allclose(coarse.direction, np.eye(3))
    assert np.allclose(coarse.direction.T @ coarse.direction, np.eye(3))
    assert np.linalg.det(coarse.direction) > 0
    assert coarse.array.min() >= -1024 and coarse.array.max() <= 3071


def test_tissue_levels_at_analytic_points(coarse):
    ph = coarse.phantom
    img = coarse.to_sitk()

    def value_at(p):
        idx = img.TransformPhysicalPointToIndex(tuple(float(x) for x in p))
        return float(coarse.array[idx[2], idx[1], idx[0]])

    assert abs(value_at(ph.centre_lps) - HU["brain"]) < 2
    # mid-skull along +x (L): skin at a_x, skull from a_x - 5 to a_x - 12
    mid_skull = ph.centre_lps + [ph.skin_semi_axes_mm[0] - ph.scalp_thickness_mm - 3.5, 0, 0]
    assert abs(value_at(mid_skull) - HU["bone"]) < 30
    mid_scalp = ph.centre_lps + [ph.skin_semi_axes_mm[0] - 2.5, 0, 0]
    assert abs(value_at(mid_scalp) - HU["scalp"]) < 30
    assert value_at(ph.centre_lps + [ph.skin_semi_axes_mm[0] + 5, 0, 0]) < -990
    # below the neck cut there is only air
    assert value_at(ph.centre_lps - [0, 0, ph.neck_cut_below_centre_mm + 4]) < -990
    for c in ph.fiducial_centres_lps:
        assert abs(value_at(c) - HU["fiducial"]) < 30


def test_partial_volume_edge_is_half_way_at_the_sphere_surface(coarse):
    """Noise-free: voxels whose centre lies on a ball's surface (air side) hold the mid value
    between air and the ball, and the profile follows the blurred-edge model."""
    ph = coarse.phantom
    pts = _lps_grid(coarse)
    vals = coarse.array.reshape(-1).astype(float)
    for c in ph.fiducial_centres_lps[:3]:
        _, n = ph.skin_point(c - ph.centre_lps)
        rel = pts - c
        d = np.linalg.norm(rel, axis=1) - ph.fiducial_radius_mm
        airside = (rel @ n) > 0.5 * ph.fiducial_radius_mm  # far from the scalp contact
        on = airside & (np.abs(d) < 0.15)
        assert on.sum() >= 3
        fill = (vals[on] - HU["air"]) / (HU["fiducial"] - HU["air"])
        assert np.all(np.abs(fill - 0.5) < 0.15)
        # a voxel 1 mm outside is mostly air, 1 mm inside mostly ball, never beyond the model
        s_lo = SAMPLE_PARAMS.psf_sigma_mm
        s_hi = np.sqrt(s_lo**2 + 1.6**2 / 12)
        band = airside & (np.abs(np.abs(d) - 1.0) < 0.1)
        f = (vals[band] - HU["air"]) / (HU["fiducial"] - HU["air"])
        lo = 0.5 * erfc(d[band] / (np.sqrt(2) * s_lo))
        hi = 0.5 * erfc(d[band] / (np.sqrt(2) * s_hi))
        assert np.all(f >= np.minimum(lo, hi) - 0.01) and np.all(f <= np.maximum(lo, hi) + 0.01)


def test_grid_covers_the_head(coarse):
    a = coarse.array
    border = np.concatenate([a[0].ravel(), a[-1].ravel(), a[:, 0].ravel(), a[:, -1].ravel(), a[:, :, 0].ravel(), a[:, :, -1].ravel()])
    assert border.max() < -900


def test_noise_level_and_determinism():
    ph = default_phantom()
    p = ScanParams(spacing_mm=(0.8, 0.8, 1.5), size=(60, 60, 20), grid_centre_lps=ph.centre_lps, noise_hu=20.0, seed=5, fov_circle=False)
    a = generate_ct(ph, p).array
    b = generate_ct(ph, p).array
    assert np.array_equal(a, b)
    c = generate_ct(ph, ScanParams(**{**p.__dict__, "seed": 6})).array
    assert not np.array_equal(a, c)
    brain = a.astype(float)  # the centre 48 x 48 mm of the brain is uniform 35 HU
    assert abs(brain.mean() - HU["brain"]) < 1.5
    assert 17.0 < brain.std() < 23.0
    # in-plane correlated, slices independent
    x = brain - brain.mean()
    r_inplane = np.mean(x[:, :, 1:] * x[:, :, :-1]) / x.var()
    r_slices = np.mean(x[1:] * x[:-1]) / x.var()
    assert r_inplane > 0.2 and abs(r_slices) < 0.05


def test_radius_and_distractors_are_sweepable():
    ph = with_radius(default_phantom(), 2.5)
    assert ph.fiducial_radius_mm == 2.5
    nod, bead = default_distractors(ph)
    ct = generate_ct(ph, ScanParams(spacing_mm=(1.0, 1.0, 1.5), size=(40, 40, 30), grid_centre_lps=nod.centre_lps, noise_hu=0.0, distractors=(nod, bead)))
    img = ct.to_sitk()
    idx = img.TransformPhysicalPointToIndex(tuple(float(x) for x in nod.centre_lps))
    assert abs(ct.array[idx[2], idx[1], idx[0]] - nod.hu) < 30
    names = [d["name"] for d in ct.truth()["distractors"]]
    assert names == ["skin clip", "bone nodule", "small bead"]


def test_bundled_sample_matches_the_phantom():
    truth = json.loads((sample_ct_path().parent / "phantom_truth.json").read_text())
    ph = default_phantom()
    assert np.allclose(truth["fiducial_centres_lps_mm"], ph.fiducial_centres_lps, atol=1e-5)
    assert truth["frame"] == "LPS" and truth["units"] == "mm"
    assert np.allclose(truth["scan"]["spacing_mm"], SAMPLE_PARAMS.spacing_mm)
    assert sample_ct_path().stat().st_size < 9e6
