"""``monotracker detect-ct`` and ``make-sample-data``: table, JSON, one-line errors."""

import json

import numpy as np
from scipy.spatial.distance import cdist

from monotracker.cli import main
from monotracker.paths import sample_ct_path
from monotracker.sim.phantom import default_phantom


def test_detect_ct_table(capsys):
    assert main(["detect-ct", str(sample_ct_path())]) == 0
    out = capsys.readouterr().out
    rows = [line.split() for line in out.splitlines() if line.strip()[:1].isdigit() and len(line.split()) == 6]
    assert len(rows) == 9
    centres = np.array([[float(x) for x in r[1:4]] for r in rows])
    assert cdist(centres, default_phantom().fiducial_centres_lps).min(axis=1).max() < 0.05


def test_detect_ct_json(capsys):
    assert main(["detect-ct", str(sample_ct_path()), "--json", "--radius", "4"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["ok"] and res["frame"] == "LPS" and len(res["fiducials"]) == 9
    c = np.array([f["centre_lps_mm"] for f in res["fiducials"]])
    assert cdist(c, default_phantom().fiducial_centres_lps).min(axis=1).max() < 0.05


def test_detect_ct_errors_are_one_line(tmp_path, capsys):
    assert main(["detect-ct", str(tmp_path / "missing.nii.gz")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: no such file") and "\n" not in err
    assert main(["detect-ct", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip().startswith("error: folder")
    assert main(["detect-ct", str(sample_ct_path()), "--radius", "-3"]) == 2
    assert "radius" in capsys.readouterr().err


def test_make_sample_data_is_deterministic(tmp_path, capsys):
    assert main(["make-sample-data", "--out", str(tmp_path)]) == 0
    a = (tmp_path / "phantom_truth.json").read_text()
    b = (sample_ct_path().parent / "phantom_truth.json").read_text()
    assert json.loads(a) == json.loads(b)
    import SimpleITK as sitk

    new = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "phantom_ct.nii.gz")))
    old = sitk.GetArrayFromImage(sitk.ReadImage(str(sample_ct_path())))
    assert np.array_equal(new, old)


def test_truncated_file_gives_only_our_line(tmp_path, capfd):
    data = sample_ct_path().read_bytes()
    import SimpleITK as sitk

    img = sitk.ReadImage(str(sample_ct_path()))
    sitk.WriteImage(img[:, :, :20], str(tmp_path / "full.mha"))
    raw = (tmp_path / "full.mha").read_bytes()
    (tmp_path / "cut.mha").write_bytes(raw[: len(raw) // 2])
    assert main(["detect-ct", str(tmp_path / "cut.mha")]) == 2
    err = capfd.readouterr().err.strip()
    assert err == "error: cannot read cut.mha: the file is truncated or corrupt"
    assert data  # the sample itself is untouched
