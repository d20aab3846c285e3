"""Fiducials beside metal denser than the balls (dental fillings, a steel rod), the fiducial kit,
touching balls and a bounded search on a pathological scan. Truth: the generator's analytic
centres; the metal objects' known positions."""

from __future__ import annotations

import numpy as np
import pytest
from ct_test_helpers import patch_params, touching_ball_scan
from scipy.spatial.distance import cdist
from test_fiducials import match

from monotracker.ct import FiducialKit, detect_fiducials
from monotracker.ct.volume import Volume
from monotracker.sim.ct_phantom import DenseBlob, generate_ct, metal_distractors
from monotracker.sim.phantom import default_phantom


def _vol(ct):
    return Volume.from_image(ct.to_sitk())


@pytest.fixture(scope="module")
def metal_ct():
    """1500 HU ceramic balls, 3071 HU fillings and a steel rod with streaks, 0.8 x 0.8 x 1.25 mm."""
    ph = default_phantom()
    return generate_ct(ph, patch_params(ph, spacing_mm=(0.8, 0.8, 1.25), fiducial_hu=1500.0,
                                        distractors=metal_distractors(ph, streak_hu=300.0)))


def test_balls_fainter_than_metal_are_all_found_and_metal_is_rejected_with_reasons(metal_ct):
    det = detect_fiducials(_vol(metal_ct))
    err, missed, false = match(det.centres, metal_ct.fiducial_centres_lps)
    assert det.ok and (missed, false) == (0, 0), det.reason
    assert err.max() < 0.1
    # every metal object is listed as rejected, near its true place, with a shape reason
    metal = np.array([b.centre_lps for b in metal_ct.params.distractors])
    rej = np.array([r.centre_lps for r in det.rejected])
    assert cdist(metal, rej).min(axis=1).max() < 3.0
    near = [r for r in det.rejected if cdist([r.centre_lps], metal).min() < 3.0]
    assert all("not round" in r.reason or "not a sphere" in r.reason for r in near), [r.reason for r in near]


def test_kit_density_rejects_a_round_metal_ball_of_the_right_size():
    ph = default_phantom()
    c0 = ph.fiducial_centres_lps[4]
    centre = ph.centre_lps + (c0 - ph.centre_lps) * 0.8  # inside the head, well away from the balls
    bead = DenseBlob(centre, np.full(3, 4.0), 3071.0, name="steel ball")
    ct = generate_ct(ph, patch_params(ph, spacing_mm=(0.8, 0.8, 1.25), fiducial_hu=1800.0, distractors=(bead,)))
    vol = _vol(ct)
    plain = detect_fiducials(vol)
    assert cdist([centre], plain.centres).min() < 0.2  # without a density a round steel ball looks like a fiducial
    kit = FiducialKit(radius_mm=4.0, density_hu=1800.0)
    det = detect_fiducials(vol, kit=kit)
    err, missed, false = match(det.centres, ct.fiducial_centres_lps)
    assert (missed, false) == (0, 0)
    assert any("density" in r.reason and np.linalg.norm(r.centre_lps - centre) < 1.0 for r in det.rejected)


def test_touching_balls_are_separated_or_reported():
    ct, truth = touching_ball_scan()
    det = detect_fiducials(_vol(ct), kit=FiducialKit(radius_mm=4.0))
    err, missed, false = match(det.centres, truth)
    found_pair = cdist(det.centres, truth[[0, 9]]).min(axis=0) < 0.3 if len(det.centres) else np.zeros(2, bool)
    if not found_pair.all():  # not separated: then reported, never silently dropped
        assert any(np.linalg.norm(r.centre_lps - (truth[0] + truth[9]) / 2) < 5.0 for r in det.rejected), [r.reason for r in det.rejected]
    assert false == 0 and missed <= 2
    assert found_pair.all(), "touching balls should be separated by the threshold ladder"
    assert err.max() < 0.15


def test_pathological_metal_head_is_bounded():
    """A fifth of the scanned region solid metal with strong streaks: the search ends with few
    listed blobs; a tight time budget stops it with a note instead of running on."""
    ph = default_phantom()
    big = DenseBlob(ph.fiducial_centres_lps.mean(axis=0) - 25.0 * ph.view_direction_lps, np.array([45.0, 40.0, 22.0]),
                    3071.0, name="metal block", streak_hu=1500.0)
    ct = generate_ct(ph, patch_params(ph, spacing_mm=(1.0, 1.0, 1.5), distractors=(big,)))
    vol = _vol(ct)
    assert np.mean(vol.array > 3000) > 0.1  # of the whole grid, air included
    det = detect_fiducials(vol)
    assert len(det.rejected) < 60
    assert any("fragments ignored" in n for n in det.notes)
    quick = detect_fiducials(vol, time_budget_s=0.0)
    assert any("search stopped" in n for n in quick.notes) and "stopped early" in quick.reason


def test_kit_round_trips_and_checks_values():
    kit = FiducialKit(radius_mm=1.5, density_hu=1600.0, name="ceramic 3 mm")
    assert FiducialKit.from_dict(kit.to_dict()) == kit
    assert FiducialKit.from_dict(None) is None
    with pytest.raises(ValueError, match="implausible"):
        FiducialKit(radius_mm=50.0)
    with pytest.raises(ValueError, match="implausible"):
        FiducialKit.from_dict({"density_hu": 10})


def test_detect_ct_lists_the_sample_clip_as_rejected(capsys):
    import json

    from monotracker.cli import main
    from monotracker.paths import sample_ct_path

    clip = np.mean(default_phantom().clip_segment_lps, axis=0)
    assert main(["detect-ct", str(sample_ct_path())]) == 0
    out = capsys.readouterr().out
    assert "rejected blob at" in out and "not round" in out
    assert main(["detect-ct", str(sample_ct_path()), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert any(np.linalg.norm(np.array(r["centre_lps_mm"]) - clip) < 2.0 for r in res["rejected"]), res["rejected"]


def test_plan_keeps_the_kit(tmp_path):
    from monotracker.engine.plan import Plan, load_plan, plan_from_dict

    plan = Plan(ct_path="x.nii.gz", fiducial_kit=FiducialKit(radius_mm=2.0, density_hu=1600.0, name="ceramic"))
    plan.save(tmp_path / "plan.json")
    back = load_plan(tmp_path / "plan.json")
    assert back.fiducial_kit == plan.fiducial_kit
    assert plan_from_dict({**plan.to_dict(), "fiducial_kit": None}).fiducial_kit is None


def test_half_embedded_3mm_balls_on_2mm_slices_with_streaks_subvoxel():
    """Radius 3 mm balls sunk half into the scalp, 2 mm slices, metal streaks (+-900 HU at the
    metal, a few hundred at the balls): every ball found, centres within 0.1 mm (a threshold +
    excess-weighted centroid is off by 0.13 mm on average here, see the benchmark)."""
    from monotracker.sim.ct_phantom import with_radius

    ph = with_radius(default_phantom(), 3.0)
    ct = generate_ct(ph, patch_params(ph, spacing_mm=(0.5, 0.5, 2.0), fiducial_embed_mm=3.0,
                                      distractors=metal_distractors(default_phantom(), streak_hu=900.0)))
    det = detect_fiducials(_vol(ct), kit=FiducialKit(radius_mm=3.0))
    err, missed, false = match(det.centres, ct.fiducial_centres_lps)
    assert (missed, false) == (0, 0), det.reason
    assert err.mean() < 0.04 and err.max() < 0.1, err
