"""The CT job (load + detection + surface) can be cancelled and has an overall timeout; a
stopped job leaves the previous CT, fiducials and plan exactly as they were. Ctrl-C in
``detect-ct`` is one line, no traceback. The load is held on a gate (no wall-clock guesses)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import SimpleITK as sitk
from ct_test_helpers import gated_load, patch_params

import monotracker.ct as ct_pkg
from monotracker.engine import Session, SessionConfig
from monotracker.errors import InputError
from monotracker.sim.ct_phantom import generate_ct
from monotracker.sim.phantom import default_phantom


@pytest.fixture(scope="module")
def patch_file(tmp_path_factory):
    ph = default_phantom()
    ct = generate_ct(ph, patch_params(ph, spacing_mm=(0.8, 0.8, 1.25)))
    path = tmp_path_factory.mktemp("patch") / "patch.nii.gz"
    sitk.WriteImage(ct.to_sitk(), str(path))
    return path


def _wait_done(s, limit_s=300.0):
    t_end = time.monotonic() + limit_s
    while time.monotonic() < t_end:
        job = s.snapshot().job
        if job is not None and job.done:
            return job
        time.sleep(0.05)
    raise AssertionError("the CT job never ended")


def _state(s):
    snap = s.snapshot()
    plan = s.plan_copy()
    return snap.ct.path, [tuple(np.round(f.centre_lps_mm, 6)) for f in snap.fiducials], plan.ct_path, plan.revision


@pytest.mark.parametrize("how", ["cancel", "timeout"])
def test_stopped_ct_job_keeps_the_previous_ct_and_plan(tmp_path, patch_file, monkeypatch, how):
    s = Session(SessionConfig(home=tmp_path / "home", clock="sim"))
    try:
        assert s.load_ct(str(patch_file)).ok
        first = s.wait_for_job(600)
        assert first.error is None, first
        before = _state(s)
        assert len(before[1]) == 9
        other = tmp_path / "other.nii.gz"
        other.write_bytes(patch_file.read_bytes())
        gate, entered = gated_load(monkeypatch)
        if how == "timeout":  # only for this job: the first load may take long on a loaded machine
            s.config.ct_job_timeout_s = 2.0
        assert s.load_ct(str(other)).ok
        assert entered.wait(60)
        if how == "cancel":
            r = s.cancel_ct_job()
            assert r.ok, r.message
        job = _wait_done(s)  # the timeout ends it by itself
        word = "cancelled by the operator" if how == "cancel" else "ran past its 2 s limit"
        assert job.error and word in job.error and "previous CT and plan are unchanged" in job.error, job
        assert "\n" not in job.error
        gate.set()  # the load finishes now; its result must be thrown away
        s.wait_for_job(600)
        assert s.snapshot().job.error == job.error
        assert _state(s) == before
        assert not s.cancel_ct_job().ok  # nothing left to cancel
        # a new load after a stopped one works
        monkeypatch.undo()
        s.config.ct_job_timeout_s = 600.0
        assert s.load_ct(str(other)).ok
        assert s.wait_for_job(600).error is None
        assert s.snapshot().ct.path == str(other)
    finally:
        s.shutdown()


def test_cancel_stops_the_fiducial_search_itself(patch_file):
    vol = ct_pkg.load_volume(patch_file)
    det = ct_pkg.detect_fiducials(vol, cancel=lambda: True)
    assert "stopped early" in det.reason and any("cancelled" in n for n in det.notes)


def test_cancel_without_a_job_is_refused(tmp_path):
    s = Session(SessionConfig(home=tmp_path / "home", clock="sim"))
    try:
        r = s.cancel_ct_job()
        assert not r.ok and r.message == "no CT job is running"
    finally:
        s.shutdown()


@pytest.mark.parametrize("bad", [0, -5, math.nan, math.inf, "60", True, 10**6])
def test_ct_job_timeout_is_validated(tmp_path, bad):
    with pytest.raises(InputError, match="ct_job_timeout_s"):
        Session(SessionConfig(home=tmp_path / "home", clock="sim", ct_job_timeout_s=bad))


def test_detect_ct_ctrl_c_is_one_line(monkeypatch, capsys, patch_file):
    from monotracker.ct import fiducials
    from monotracker.cli import main

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(fiducials, "detect_fiducials", interrupted)
    assert main(["detect-ct", str(patch_file)]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "interrupted" in err[0] and "Traceback" not in err[0], err


def test_cancelled_kit_detection_leaves_the_plans_kit_and_fiducials(tmp_path, patch_file, monkeypatch):
    """A new kit with a CT loaded is committed together with the fiducials it finds: when that
    detection is cancelled the plan keeps its old kit and fiducials (review finding)."""
    s = Session(SessionConfig(home=tmp_path / "home", clock="sim"))
    try:
        assert s.load_ct(str(patch_file)).ok
        assert _wait_done(s).error is None
        before = _state(s)
        gate, entered = gated_load(monkeypatch, "detect_fiducials")
        assert s.set_fiducial_kit(2.5, 1700.0).ok
        assert entered.wait(120)
        assert s.plan_copy().fiducial_kit is None  # not yet: it comes with the fiducials
        assert s.cancel_ct_job().ok
        gate.set()
        job = _wait_done(s)
        assert job.done and job.error
        s.wait_for_job(300)
        assert s.plan_copy().fiducial_kit is None and _state(s) == before
        assert not s.audit_entries(code="fiducial_kit_set")
    finally:
        s.shutdown()
