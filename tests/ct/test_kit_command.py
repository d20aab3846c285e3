"""``Session.set_fiducial_kit``: validated, kept in the plan (and a restored plan), re-runs the
detection on the loaded CT as the CT job, audited; the snapshot lists the rejected blobs.
Truth: the generator's analytic ball centres and the known place of a round steel ball."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from ct_test_helpers import patch_params
from scipy.spatial.distance import cdist

from monotracker.engine import Session, SessionConfig
from monotracker.engine.plan import load_plan
from monotracker.sim.ct_phantom import DenseBlob, generate_ct
from monotracker.sim.phantom import default_phantom


@pytest.fixture(scope="module")
def steel_ct(tmp_path_factory):
    """1800 HU balls and a round 3071 HU steel ball of the same size inside the head."""
    ph = default_phantom()
    c0 = ph.fiducial_centres_lps[4]
    centre = ph.centre_lps + (c0 - ph.centre_lps) * 0.8
    ct = generate_ct(ph, patch_params(ph, spacing_mm=(0.8, 0.8, 1.25), fiducial_hu=1800.0,
                                      distractors=(DenseBlob(centre, np.full(3, 4.0), 3071.0, name="steel ball"),)))
    path = tmp_path_factory.mktemp("steel") / "steel.nii.gz"
    sitk.WriteImage(ct.to_sitk(), str(path))
    return path, ct.fiducial_centres_lps, centre


def _wait(s):
    job = s.wait_for_job(600)
    assert job is not None and job.done, job
    return job


def test_kit_reruns_detection_keeps_the_plan_and_is_audited(tmp_path, steel_ct):
    path, truth, steel = steel_ct
    home = tmp_path / "home"
    s = Session(SessionConfig(home=home, clock="sim"))
    try:
        assert s.load_ct(str(path)).ok
        assert _wait(s).error is None
        snap = s.snapshot()
        centres = np.array([f.centre_lps_mm for f in snap.fiducials])
        assert cdist([steel], centres).min() < 0.5  # without a density the steel ball looks like a ball
        # refusals: one line each, nothing changes
        for bad in [(float("nan"), None), (50.0, None), ("4", None), (True, None), (4.0, float("inf")), (4.0, 100.0), (None, 1800.0)]:
            r = s.set_fiducial_kit(*bad)
            assert not r.ok and "\n" not in r.message and r.message, bad
        assert s.plan_copy().fiducial_kit is None
        r = s.set_fiducial_kit(4.0, 1800.0)
        assert r.ok, r.message
        job = _wait(s)
        assert job.error is None and job.name == "detect_fiducials", job
        snap = s.snapshot()
        centres = np.array([f.centre_lps_mm for f in snap.fiducials])
        assert len(centres) == len(truth) and cdist(centres, truth).min(axis=1).max() < 0.1
        assert all(f.status == "detected" for f in snap.fiducials)
        # the steel ball is listed in the snapshot as rejected, for its density
        near = [b for b in snap.ct.rejected if np.linalg.norm(np.array(b.centre_lps_mm) - steel) < 1.0]
        assert near and "density" in near[0].reason and 3.0 < near[0].radius_mm < 5.0 and near[0].n_voxels > 0, snap.ct.rejected
        kit = load_plan(home / "plan.json").fiducial_kit
        assert (kit.radius_mm, kit.density_hu) == (4.0, 1800.0)
        rows = s.audit_entries(code="fiducial_kit_set")
        assert rows and rows[-1].data["kit"]["density_hu"] == 1800.0
        # locked fiducials: a new kit is refused (it would replace them)
        for f in s.snapshot().fiducials:
            assert s.set_fiducial_status(f.id, "confirmed").ok
        assert s.confirm_fiducials().ok
        r = s.set_fiducial_kit(3.0)
        assert not r.ok and "locked" in r.message
    finally:
        s.shutdown()
    s2 = Session(SessionConfig(home=home, clock="sim"))  # the kit survives a restart
    try:
        kit = s2.plan_copy().fiducial_kit
        assert (kit.radius_mm, kit.density_hu) == (4.0, 1800.0)
    finally:
        s2.shutdown()


def test_kit_without_a_ct_is_kept_and_used_by_the_next_load(tmp_path, steel_ct):
    path, truth, steel = steel_ct
    s = Session(SessionConfig(home=tmp_path / "home", clock="sim"))
    try:
        r = s.set_fiducial_kit(4.0, 1800.0)
        assert r.ok and "when a CT is loaded" in r.message
        assert s.load_ct(str(path)).ok
        assert _wait(s).error is None
        centres = np.array([f.centre_lps_mm for f in s.snapshot().fiducials])
        assert cdist([steel], centres).min() > 3.0
        assert len(centres) == len(truth)
    finally:
        s.shutdown()
