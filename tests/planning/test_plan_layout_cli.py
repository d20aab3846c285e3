"""``monotracker plan-layout``: the report on the sample CT ends with a JSON line holding the
suggestion, the camera pose and the predictions; bad input gets one line, never a traceback."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from monotracker.cli import main
from monotracker.paths import sample_ct_path
from monotracker.sim.phantom import default_phantom

PH = default_phantom()


def _xyz(p) -> str:
    return ",".join(f"{v:.3f}" for v in p)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """One quick plan of 7 balls on the sample CT (text + JSON)."""
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["plan-layout", str(sample_ct_path()), "--target", _xyz(PH.sample_target_lps),
                     "--entry", _xyz(PH.sample_entry_lps), "--balls", "7", "--quick"])
    return code, out.getvalue(), err.getvalue()


def test_report_ends_with_a_json_object(report):
    code, out, _ = report
    assert code == 0
    lines = out.strip().splitlines()
    d = json.loads(lines[-1])
    assert d["frame"] == "LPS" and len(d["balls_lps_mm"]) == 7
    T = np.array(d["T_ct_cam"])
    assert T.shape == (4, 4) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-5)
    exp = d["expected"]
    assert exp["balls_seen"] == 7 and exp["all_seen"]["p95_mm"] > exp["all_seen"]["mean_mm"] > 0
    assert exp["worst_hidden"]["rms_mm"] >= exp["all_seen"]["rms_mm"]
    assert d["at_near_distance"]["all_seen"]["rms_mm"] <= d["at_far_distance"]["all_seen"]["rms_mm"]
    # the CT's own nine balls, found in the CT, evaluated too
    assert len(d["ct_fiducials_lps_mm"]) == 9
    got = np.array(d["ct_fiducials_lps_mm"])
    assert np.linalg.norm(got[:, None] - PH.fiducial_centres_lps[None], axis=2).min(axis=1).max() < 0.5
    assert d["existing_from_planned_camera"]["all_seen"] is not None
    # the simulated camera's lens images the kit's balls at 11 px from 400 mm: inside the judged range
    assert not any("short lens" in n for n in d["notes"]) and "short lens" not in out
    # the CT's balls the planned camera sees with little skin around them are named in a note,
    # the same ones the JSON's per-ball shares put under the planner's rule (none of the new ones)
    from monotracker.planning.visibility import PLACE_MIN_SKIN_AROUND

    around = d["existing_from_planned_camera"]["skin_around"]
    short = sorted(int(k) for k, a in around.items() if a < PLACE_MIN_SKIN_AROUND)   # all 9: index == CT id
    assert d["ct_fiducials_short_of_skin"] == short
    notes = [ln for ln in lines if ln.startswith("note: CT fiducial")]
    assert len(notes) == (1 if short else 0), notes
    assert sorted(int(m) for n in notes for m in re.findall(r"#(\d+)", n)) == short, (notes, short)
    # ... and the outlook counts them as found less often, the JSON and the text alike
    lo = d["existing_from_planned_camera"]["with_detector_losses"]
    assert lo["balls_short_of_skin"] == len(short)
    if short:
        assert lo["found_probability_short_of_skin"] < lo["found_probability"]
        assert f"({len(short)} on the head's outline or beside the drape at" in out
    new = [str(i) for i, src in enumerate(d["balls_from_existing"]) if src < 0] if "balls_from_existing" in d else []
    assert all(d["expected"]["skin_around"][k] >= PLACE_MIN_SKIN_AROUND for k in new)
    # the text names the same positions and the same camera
    assert "suggested balls (centre, LPS mm):" in out and "T_ct_cam" in out
    # (the JSON's three decimals and the text's two round independently: compare the numbers)
    first = np.array(d["balls_lps_mm"][0])
    line = next(ln for ln in lines if ln.strip().startswith("1:"))
    assert np.allclose([float(x) for x in line.split(":")[1].split()[:3]], first, atol=0.006), (line, first)


@pytest.mark.parametrize("args, expected", [
    (["--target", "1,2"], "--target: '1,2' is not 3 numbers X,Y,Z"),
    (["--target", "0,0,900"], "error: the target lies outside the head surface's extent; check its LPS coordinates"),
    (["--target", "0,0,0", "--balls", "3"], "--balls: 3 must be >= 4"),
    (["--target", "0,0,0", "--keep", "12"], "error: --keep 12: the CT has fiducials 0-8"),
    (["--target", "0,0,0", "--camera", "/nonexistent/cam.yaml"], "file not found: /nonexistent/cam.yaml"),
])
def test_bad_input_gets_one_line(capsys, args, expected):
    try:
        code = main(["plan-layout", str(sample_ct_path()), *args, "--quick"])
    except SystemExit as exc:          # argparse's own refusals
        code = exc.code
    cap = capsys.readouterr()
    assert code == 2
    err = cap.err.strip().splitlines()
    assert expected in err[-1] and "Traceback" not in cap.err, cap.err
    assert cap.out == ""


def test_missing_ct_gets_one_line(capsys, tmp_path):
    code = main(["plan-layout", str(tmp_path / "nope.nii.gz"), "--target", "0,0,0"])
    cap = capsys.readouterr()
    assert code == 2 and len(cap.err.strip().splitlines()) == 1 and cap.err.startswith("error: ")


def test_a_short_lens_is_named_in_the_report(tmp_path, capsys):
    """A calibration with f = 800 px (the rendered sets' short lens) images the balls at 8 px from
    the planner's closest distance: the report's notes say so, in the text and in the JSON."""
    from monotracker.vision.camera_model import CameraModel, default_camera

    cam = default_camera()
    K = cam.K.copy()
    K[0, 0] = K[1, 1] = 800.0
    path = CameraModel(K, cam.dist, cam.image_size).save(tmp_path / "wide.yml")
    code = main(["plan-layout", str(sample_ct_path()), "--target", _xyz(PH.sample_target_lps), "--balls", "4",
                 "--quick", "--camera", str(path)])
    out = capsys.readouterr().out
    assert code == 0
    d = json.loads(out.strip().splitlines()[-1])
    assert sum("short lens" in n and "8.0 px" in n for n in d["notes"]) == 1
    assert any(ln.startswith("note: short lens") for ln in out.splitlines())
