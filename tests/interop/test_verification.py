"""Accuracy verification before the robot moves, on the twin (point level and rendered): validation
fiducials are kept out of the fit, their live error is shown, and a displaced one blocks arming."""

import json

import numpy as np
import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.sim.phantom import default_phantom

VALIDATION = (1, 6)


def _plan(s: Session, displace_mm: float = 0.0) -> None:
    """The phantom's fiducials (operator-added), 1 and 6 as validation fiducials; fiducial 6's CT
    centre optionally moved ``displace_mm`` along LPS x (as if the ball moved after the CT)."""
    ph = default_phantom()
    for i, c in enumerate(ph.fiducial_centres_lps):
        c = np.array(c, float)
        if i == VALIDATION[1]:
            c[0] += displace_mm
        assert s.add_fiducial(c, ph.fiducial_radius_mm).ok
    for fid in VALIDATION:
        assert s.set_fiducial_role(fid, "validation").ok
    assert s.confirm_fiducials().ok
    assert s.use_sample_plan().ok


def _acquire(s: Session, max_s: float = 5.0):
    for _ in range(int(max_s / 0.1)):
        s.advance(0.1)
        p = s.snapshot().pose
        if p is not None and p.trusted and p.validation_tre_mm:
            return p
    raise AssertionError(f"no trusted pose: {s.snapshot().pose}")


@pytest.mark.parametrize("camera", ["sim-points", "sim"])
def test_validation_error_shown_and_arming_allowed(tmp_path, camera):
    s = Session(SessionConfig(home=tmp_path, camera=camera, clock="sim"))
    try:
        _plan(s)
        plan = s.plan_copy()
        assert [f.id for f in plan.validation_fiducials()] == list(VALIDATION)
        assert len(plan.registration_centres()) == 7
        assert s.start_camera().ok
        p = _acquire(s)
        assert set(p.validation_tre_mm) == set(VALIDATION)
        assert p.validation_ok and max(p.validation_tre_mm.values()) < 0.6, p.validation_tre_mm
        assert set(p.residuals_px) == set(range(9)) - set(VALIDATION)  # not used in the fit
        assert p.fre_mm is not None and p.predicted_tre_mm is not None
        r = s.arm("1234")
        assert r.ok, r.message
        rep = json.loads((tmp_path / "verification.json").read_text())
        assert rep["decision"] == "armed" and rep["validation"]["ok"]
        assert set(rep["validation"]["errors_mm"]) == {str(v) for v in VALIDATION}
    finally:
        s.shutdown()


@pytest.mark.parametrize("camera", ["sim-points", "sim"])
def test_a_displaced_validation_fiducial_blocks_arming(tmp_path, camera):
    s = Session(SessionConfig(home=tmp_path, camera=camera, clock="sim"))
    try:
        _plan(s, displace_mm=3.0)
        assert s.start_camera().ok
        p = _acquire(s)
        assert p.trusted  # the registration itself looks fine (FRE small): only validation catches it
        assert p.validation_ok is False and p.validation_tre_mm[VALIDATION[1]] > 1.5
        assert p.validation_tre_mm[VALIDATION[0]] < 0.6
        r = s.arm("1234")
        assert not r.ok and f"validation fiducial {VALIDATION[1]}" in r.message
        assert s.snapshot().robot.state == "disarmed"
        rep = json.loads((tmp_path / "verification.json").read_text())
        assert rep["decision"] == "refused" and f"validation fiducial {VALIDATION[1]}" in rep["refusal"]
        assert any(a.code == "arm_refused" for a in s.snapshot().alerts)
    finally:
        s.shutdown()


def test_roles_keep_enough_registration_fiducials_and_survive_a_restart(tmp_path):
    s = Session(SessionConfig(home=tmp_path, clock="sim", min_fiducials=4))
    ph = default_phantom()
    try:
        for c in ph.fiducial_centres_lps[:5]:
            assert s.add_fiducial(c, ph.fiducial_radius_mm).ok
        assert s.set_fiducial_role(0, "validation").ok
        r = s.set_fiducial_role(1, "validation")
        assert not r.ok and "only 3 fiducials would remain" in r.message
        assert not s.set_fiducial_role(2, "reference").ok
        assert s.confirm_fiducials().ok
        assert not s.set_fiducial_role(0, "registration").ok  # locked
    finally:
        s.shutdown()
    s2 = Session(SessionConfig(home=tmp_path, clock="sim"))
    try:
        assert [f.id for f in s2.plan_copy().validation_fiducials()] == [0]
    finally:
        s2.shutdown()
