"""The Register step shows the validation fiducials' live error and the recording state; the CT
step's table marks validation fiducials. Rendered from the engine's own snapshot types."""

from __future__ import annotations

import numpy as np

from monotracker.engine.snapshot import Fiducial, PoseSummary, RecordingSummary


def _pose(**kw) -> PoseSummary:
    base = dict(t=1.0, age_s=0.02, ok=True, trusted=True, reason="", T_cam_ct=np.eye(4), n_visible=7,
                fiducial_status={}, residuals_px={}, fre_mm=0.2, predicted_tre_mm=0.4, latency_ms=40.0)
    base.update(kw)
    return PoseSummary(**base)


def test_validation_line_says_verified_or_refused_with_each_error():
    from monotracker.ui.step_register import validation_line

    assert validation_line(None) == ""
    assert validation_line(_pose()) == ""  # no validation fiducials in the plan: nothing to show
    ok = validation_line(_pose(validation_tre_mm={7: 0.31, 8: 0.52}, validation_ok=True))
    assert "data-ok='1'" in ok and "VERIFIED" in ok and "#7 0.31 mm" in ok and "#8 0.52 mm" in ok
    bad = validation_line(_pose(validation_tre_mm={7: 2.74, 8: None}, validation_ok=False,
                                validation_reason="fiducial 7 is 2.7 mm from its viewing ray"))
    assert "data-ok='0'" in bad and "arming refused" in bad and "#8 not seen" in bad and "2.7 mm" in bad


def test_recording_line_and_validation_role_in_the_fiducial_table():
    from types import SimpleNamespace

    from monotracker.ui.step_ct import fiducial_table
    from monotracker.ui.step_register import recording_line

    assert recording_line(SimpleNamespace(recording=None)) == ""
    line = recording_line(SimpleNamespace(recording=RecordingSummary("/tmp/rec", 120, True, dropped=2)))
    assert "RECORDING" in line and "120 frames" in line and "2 dropped" in line
    snap = SimpleNamespace(fiducials_locked=False, fiducials=(
        Fiducial(0, np.zeros(3), 4.0, 0.9, "confirmed"),
        Fiducial(1, np.ones(3), 4.0, 0.9, "confirmed", role="validation")))
    table = fiducial_table(snap)
    assert table.count("validation: not in the fit") == 1
