"""The saved session cannot lie about what it was made on (issue 17 item 2): the plan records
content hashes of the CT and the calibration file; a changed or missing CT, or a changed
calibration, raises an alarm and needs the operator's re-confirmation before arming."""

import json
import shutil

import numpy as np
import pytest
import SimpleITK as sitk

from monotracker.engine import Session, SessionConfig
from monotracker.engine.integrity import content_sha256
from monotracker.paths import sample_ct_path


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    """A plan made on a private copy of the sample CT; returns (home, ct_path)."""
    base = tmp_path_factory.mktemp("planned")
    ct = base / "ct.nii.gz"
    shutil.copy(sample_ct_path(), ct)
    home = base / "home"
    s = Session(SessionConfig(home=home, clock="sim"))
    try:
        assert s.load_ct(ct).ok and s.wait_for_job(180).error is None
        for f in s.snapshot().fiducials:
            s.set_fiducial_status(f.id, "confirmed")
        assert s.confirm_fiducials().ok and s.use_sample_plan().ok
        assert s.plan_not_ready() is None
    finally:
        s.shutdown()
    d = json.loads((home / "plan.json").read_text())
    assert d["integrity"]["ct_sha256"] == content_sha256(ct)
    return home, ct


def _copy_home(planned, tmp_path, ct_to=None):
    home, ct = planned
    new_ct = tmp_path / "ct.nii.gz"
    shutil.copy(ct, new_ct)
    h = tmp_path / "home"
    h.mkdir()
    d = json.loads((home / "plan.json").read_text())
    d["ct_path"] = str(new_ct)
    from monotracker.engine.integrity import stamp_plan_dict

    (h / "plan.json").write_text(json.dumps(stamp_plan_dict(d)))  # as the app would have written it
    return h, new_ct


def _session_with_ct(home):
    s = Session(SessionConfig(home=home, clock="sim"))
    ct = s.plan_copy().ct_path
    assert s.load_ct(ct).ok and s.wait_for_job(180).error is None
    return s


def test_same_ct_restores_without_alarm(planned, tmp_path):
    home, _ = _copy_home(planned, tmp_path)
    s = _session_with_ct(home)
    try:
        assert not [a for a in s.snapshot().alerts if a.level == "alarm"], s.snapshot().alerts
        assert s.plan_not_ready() is None
    finally:
        s.shutdown()


def test_changed_ct_needs_reconfirmation(planned, tmp_path):
    home, ct = _copy_home(planned, tmp_path)
    img = sitk.ReadImage(str(ct))
    a = sitk.GetArrayFromImage(img)
    a[0, 0, 0] += 7  # one voxel in a corner: same fiducials, different scan file
    out = sitk.GetImageFromArray(a)
    out.CopyInformation(img)
    sitk.WriteImage(out, str(ct))
    s = _session_with_ct(home)
    try:
        assert any(al.code == "plan_ct_changed" for al in s.snapshot().alerts)
        why = s.plan_not_ready()
        assert why and "re-confirm" in why and "changed" in why
        assert not s.arm("1234").ok
        assert s.reconfirm_plan().ok
        assert s.plan_not_ready() is None
    finally:
        s.shutdown()
    s2 = _session_with_ct(home)  # the new CT's hash was recorded with the re-confirmation
    try:
        assert not any(al.code == "plan_ct_changed" for al in s2.snapshot().alerts)
        assert s2.plan_not_ready() is None
    finally:
        s2.shutdown()


def test_missing_ct_raises_an_alarm_and_blocks_arming(planned, tmp_path):
    home, ct = _copy_home(planned, tmp_path)
    ct.unlink()
    s = Session(SessionConfig(home=home, clock="sim"))
    try:
        assert any(al.code == "plan_ct_missing" for al in s.snapshot().alerts)
        assert "CT is not loaded" in s.plan_not_ready()
        assert not s.arm("1234").ok
    finally:
        s.shutdown()


def test_changed_calibration_file_needs_reconfirmation(tmp_path):
    from .conftest import plan_sample

    cal = tmp_path / "cam.json"
    K = np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]])
    cal.write_text(json.dumps({"camera_matrix": K.tolist(), "distortion_coefficients": [0.0] * 5,
                               "image_width": 1280, "image_height": 720}))
    s = Session(SessionConfig(home=tmp_path / "h", clock="sim"))
    try:
        plan_sample(s)
        assert s._plan.store_camera("device:0", str(cal), K, np.zeros(5), (1280, 720)) is None
        assert s.plan_copy().integrity["calibration_sha256"] == content_sha256(cal)
        assert s.plan_not_ready() is None
        cal.write_text(cal.read_text().replace("900.0", "905.0"))  # recalibrated behind the plan's back
        assert s._plan.store_camera("device:0", str(cal), K * [[1.0], [1.0], [1.0]], np.zeros(5), (1280, 720)) is None
        assert any(al.code == "calibration_changed" for al in s.snapshot().alerts)
        assert "re-confirm" in s.plan_not_ready()
        assert s.reconfirm_plan().ok and s.plan_not_ready() is None
        # a calibration the checks refuse is not stored at all
        why = s._plan.store_camera("device:0", None, np.array([[-1.0, 0, 640], [0, 900, 360], [0, 0, 1]]), None, (1280, 720))
        assert why and "focal" in why
        assert np.allclose(s.plan_copy().K, K)
    finally:
        s.shutdown()
