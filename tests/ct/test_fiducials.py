"""Fiducial detection against the generator's analytic centres (independent truth)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from monotracker.ct import FiducialKit, detect_fiducials, detect_fiducials_paper, load_volume
from monotracker.paths import sample_ct_path
from monotracker.sim.phantom import default_phantom


def match(found: np.ndarray, truth: np.ndarray, tol_mm: float = 1.0):
    """Errors of the found centres matched to the nearest truth; counts of missed and false."""
    if len(found) == 0:
        return np.zeros(0), len(truth), 0
    D = cdist(found, truth)
    nearest = D.min(axis=1)
    false = int(np.sum(nearest > tol_mm))
    hit = np.unique(D.argmin(axis=1)[nearest <= tol_mm])
    return nearest[nearest <= tol_mm], len(truth) - len(hit), false


def test_sample_ct_all_fiducials_found_with_subvoxel_accuracy():
    vol = load_volume(sample_ct_path())
    det = detect_fiducials(vol)
    truth = default_phantom().fiducial_centres_lps
    err, missed, false = match(det.centres, truth)
    assert det.ok, det.reason
    assert (missed, false) == (0, 0)
    assert err.mean() < 0.05 and err.max() < 0.1
    assert np.allclose(det.radii_mm, 4.0, atol=0.1)
    assert all(0.0 < f.score <= 1.0 for f in det.fiducials)


def test_patch_05x05x10_oblique_noisy(patch_volume, patch_ct):
    det = detect_fiducials(patch_volume, radius_mm=4.0)
    err, missed, false = match(det.centres, patch_ct.fiducial_centres_lps)
    assert (missed, false) == (0, 0), det.reason
    assert err.mean() < 0.05


@pytest.fixture(scope="module")
def distracted_ct():
    """Patch with a dense bone nodule, a small bead and metal streaks from the clip."""
    from ct_test_helpers import patch_params

    from monotracker.sim.ct_phantom import default_distractors, generate_ct

    ph = default_phantom()
    return generate_ct(ph, patch_params(psf_sigma_mm=0.3, metal_streak_hu=2000.0, distractors=default_distractors(ph)))


def test_distractors_rejected_with_reasons(distracted_ct):
    from monotracker.ct.volume import Volume

    vol = Volume.from_image(distracted_ct.to_sitk())
    det = detect_fiducials(vol)
    err, missed, false = match(det.centres, distracted_ct.fiducial_centres_lps)
    assert (missed, false) == (0, 0), det.reason
    assert err.mean() < 0.05
    assert det.rejected and all(r.reason for r in det.rejected)
    # the nodule (elongated ellipsoid in the skull) is among the rejected, as not round
    nodule = distracted_ct.params.distractors[0].centre_lps
    near = [r for r in det.rejected if np.linalg.norm(r.centre_lps - nodule) < 3.0]
    assert near and "not round" in near[0].reason
    # the paper's recipe takes the distractors as fiducials
    base = detect_fiducials_paper(vol)
    _, _, base_false = match(base.centres, distracted_ct.fiducial_centres_lps)
    assert base_false >= 2


def test_paper_baseline_runs_and_is_less_accurate(patch_volume, patch_ct):
    base = detect_fiducials_paper(patch_volume)
    ours = detect_fiducials(patch_volume)
    truth = patch_ct.fiducial_centres_lps
    e_base, _, _ = match(base.centres, truth)
    e_ours, _, _ = match(ours.centres, truth)
    assert base.ok and len(e_base) == 9
    assert e_ours.mean() < e_base.mean()


def test_no_fiducials_is_not_an_error():
    from monotracker.ct.volume import Volume
    from monotracker.sim.ct_phantom import ScanParams, generate_ct

    ph = default_phantom()
    # the left-posterior side of the head: scalp, skull, brain, air; no balls, no clip
    ct = generate_ct(ph, ScanParams(spacing_mm=(0.8, 0.8, 1.5), size=(70, 70, 30), grid_centre_lps=ph.centre_lps + [60.0, 45.0, -10.0]))
    det = detect_fiducials(Volume.from_image(ct.to_sitk()))
    assert not det.ok and det.fiducials == [] and det.centres.shape == (0, 3)
    # bone is searched too (the balls may be fainter than metal); nothing there is a ball
    assert "none is a sphere" in det.reason or "no sphere-shaped blob" in det.reason, det.reason
    assert all("sphere" in r.reason or "round" in r.reason or "large" in r.reason for r in det.rejected)


def test_wrong_nominal_radius_rejects_with_reason(patch_volume):
    det = detect_fiducials(patch_volume, radius_mm=2.0)
    assert not det.ok and "the kit's radius is 2 mm but the scan holds 9 round balls of radius 4.0 mm" in det.reason, det.reason
    assert sum("wrong size" in r.reason for r in det.rejected) == 9


def test_a_kit_radius_far_too_small_is_named_not_blamed_on_bone_or_touching_balls(patch_volume, patch_ct):
    """Issue 36: a kit radius of 0.6 mm (a typo for 6, or mm for cm) on a scan of 4 mm balls
    said the balls were "too large: bone, implant or metal" and the steel clip "touching balls
    that could not be separated?"; the reason now names the kit's radius and the scan's."""
    det = detect_fiducials(patch_volume, kit=FiducialKit(radius_mm=0.6))
    assert not det.ok and not det.fiducials
    assert "kit's radius is 0.6 mm" in det.reason and "9 round balls of radius 4.0 mm" in det.reason, det.reason
    truth = patch_ct.fiducial_centres_lps
    at_balls = [r for r in det.rejected if cdist([r.centre_lps], truth).min() < 1.0]
    assert len(at_balls) == 9 and all("round ball of radius 4.0" in r.reason for r in at_balls), [r.reason for r in at_balls]
    assert not any("touching balls" in r.reason or "bone, implant or metal" in r.reason for r in det.rejected), \
        [r.reason for r in det.rejected]


def test_estimated_radius_for_other_ball_sizes():
    from ct_test_helpers import patch_params

    from monotracker.ct.volume import Volume
    from monotracker.sim.ct_phantom import generate_ct, with_radius

    ph = with_radius(default_phantom(), 2.5)
    ct = generate_ct(ph, patch_params(ph, spacing_mm=(0.6, 0.6, 1.2), noise_hu=25.0))
    det = detect_fiducials(Volume.from_image(ct.to_sitk()))
    err, missed, false = match(det.centres, ct.fiducial_centres_lps)
    assert (missed, false) == (0, 0)
    assert err.mean() < 0.05
    assert np.allclose(det.radii_mm, 2.5, atol=0.1)


def test_result_json_and_order(patch_volume):
    import json

    det = detect_fiducials(patch_volume)
    d = json.loads(json.dumps(det.to_dict()))
    assert d["frame"] == "LPS" and d["units"] == "mm" and len(d["fiducials"]) == 9
    s = det.centres[:, 2]
    assert np.all(np.diff(s) <= 0)  # superior first
