"""A plan edited outside the app is visible (issue 36): the audit chain knows every plan the app
saved (a durable ``plan_saved`` row written before the file) and the file carries this machine's
MAC; a file that is neither is kept aside and the app's own last plan restored.

Before: plan.json edited behind the app with its (unkeyed) content hash recomputed was restored
and used (target moved, hand-eye rotated 2 deg / shifted 5 mm, fiducials shifted 10 mm); with a
stale hash the operator re-confirmed and the edited plan was used.
"""

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.engine.integrity import plan_content_sha256
from monotracker.geometry import rotation_about_axis
from monotracker.sim.or_layout import default_layout

from .conftest import alerts_of as _alerts
from .conftest import plan_sample
from .conftest import restart as _restart
from .conftest import saved_plan as _saved_plan

ROOT = Path(__file__).resolve().parents[2]


def _target_moved(d):
    d["target_lps_mm"][2] += 10.0


def _hand_eye_rotated(d):
    T = np.array(d["T_base_cam_mm"])
    R = rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.radians(2.0))
    T[:3, :3] = T[:3, :3] @ R
    d["T_base_cam_mm"] = T.tolist()


def _hand_eye_shifted(d):
    T = np.array(d["T_base_cam_mm"])
    T[:3, 3] += np.array([3.0, 4.0, 0.0])  # 5 mm
    d["T_base_cam_mm"] = T.tolist()


def _fiducial_shifted(d):
    d["fiducials"][3]["centre_lps_mm"][0] += 10.0


def _all_three(d):
    _target_moved(d)
    _hand_eye_rotated(d)
    _fiducial_shifted(d)


def _rehash(d):
    """What someone editing the file would do: recompute the unkeyed content hash (the stale
    MAC left in, or taken out)."""
    d["integrity"]["plan_sha256"] = plan_content_sha256(d)


CASES = [
    (_target_moved, "target moved 10.0 mm"),
    (_hand_eye_rotated, "hand-eye rotated 2.0 deg"),
    (_hand_eye_shifted, "hand-eye shifted 5.0 mm"),
    (_fiducial_shifted, "fiducial 3 moved 10.0 mm"),
    (_all_three, "target moved 10.0 mm; hand-eye rotated 2.0 deg; fiducial 3 moved 10.0 mm"),
]


@pytest.mark.parametrize("hashing", ["recomputed", "recomputed, MAC removed", "stale"])
@pytest.mark.parametrize("edit,words", CASES, ids=[c[0].__name__.strip("_") for c in CASES])
def test_a_plan_edited_outside_the_app_is_kept_aside_and_never_used(tmp_path, edit, words, hashing):
    home = tmp_path / "home"
    own = _saved_plan(home)
    d = json.loads(json.dumps(own))
    edit(d)
    if hashing != "stale":
        _rehash(d)
    if hashing == "recomputed, MAC removed":
        d["integrity"].pop("plan_mac")
        _rehash(d)
    edited_text = json.dumps(d)
    (home / "plan.json").write_text(edited_text)

    s = _restart(home)
    try:
        al = _alerts(s, "plan_changed_outside")
        assert al and words in al[0].message, [a.message for a in s.snapshot().alerts]
        assert "the app's last plan" in al[0].message
        # the edited file is kept aside, byte for byte; the plan in use is the app's own
        aside = sorted(home.glob("plan.changed-outside-*.json"))
        assert len(aside) == 1 and aside[0].read_text() == edited_text
        plan = s.plan_copy()
        assert np.array_equal(plan.target_lps_mm, own["target_lps_mm"])
        assert np.array_equal(plan.entry_lps_mm, own["entry_lps_mm"])
        assert np.array_equal(plan.T_base_cam, own["T_base_cam_mm"])
        assert [f.centre_lps_mm.tolist() for f in plan.fiducials] == [f["centre_lps_mm"] for f in own["fiducials"]]
        # the operator looks before arming; re-confirming keeps the app's plan, not the edit
        assert "plan_reconfirm_pending" in [a.code for a in s.snapshot().alarms]
        assert s.start_camera().ok
        s.advance(0.3)
        r = s.arm("1234")
        assert not r.ok and "re-confirm" in r.message
        assert s.reconfirm_plan().ok
        assert np.array_equal(s.plan_copy().target_lps_mm, own["target_lps_mm"])
        r = s.arm("1234")
        assert r.ok, r.message
    finally:
        s.shutdown()
    s2 = _restart(home)  # what the app wrote back is its own: no alarm at the next start
    try:
        assert not _alerts(s2, "plan_changed_outside") and s2.plan_not_ready() is None
    finally:
        s2.shutdown()


def test_every_save_writes_its_plan_saved_row_first(tmp_path):
    """The audit chain's newest plan_saved row is the plan on disk after every command."""
    home = tmp_path / "home"
    s = Session(SessionConfig(home=home, clock="sim"))
    try:
        plan_sample(s)
        assert s.set_hand_eye(default_layout().T_base_cam).ok
        rows = s.audit_entries(code="plan_saved")
        on_disk = json.loads((home / "plan.json").read_text())
        assert rows[-1].data["plan_sha256"] == plan_content_sha256(on_disk)
        assert rows[-1].data["plan"]["revision"] == on_disk["revision"]
        # each row names the digest of the plan it replaces: an unbroken line of saves
        for a, b in zip(rows, rows[1:]):
            assert b.data["previous_sha256"] == a.data["plan_sha256"]
        assert len(rows) >= 10  # 9 fiducials added, locked, entry, target, hand-eye
    finally:
        s.shutdown()


_KILL_CHILD = r'''
import os, signal, sys
import numpy as np
from monotracker.engine import Session, SessionConfig
from monotracker.engine.plan import store
s = Session(SessionConfig(home=sys.argv[1], clock="sim"))
def die(*a, **k):
    os.kill(os.getpid(), signal.SIGKILL)  # after the row, before the file
store.atomic_write_json = die
print("SAVING", flush=True)
s.set_hand_eye(np.eye(4))
'''


def test_kill_9_between_the_row_and_the_file_is_not_taken_for_an_edit(tmp_path):
    home = tmp_path / "home"
    own = _saved_plan(home)
    env = dict(os.environ, PYTHONPATH=str(ROOT / "app"))
    p = subprocess.run([sys.executable, "-c", _KILL_CHILD, str(home)], capture_output=True, text=True,
                       env=env, cwd=ROOT, timeout=300)
    assert p.returncode == -signal.SIGKILL and "SAVING" in p.stdout, p.stderr[-2000:]
    assert json.loads((home / "plan.json").read_text()) == own  # the file was never written
    s = _restart(home)
    try:
        rows = s.audit_entries(code="plan_saved")
        lost = [r for r in rows if r.data["plan"]["T_base_cam_mm"] == np.eye(4).tolist()]
        assert lost, "the change's row was written before the file"
        assert not _alerts(s, "plan_changed_outside") and not [a for a in s.snapshot().alarms if a.level == "alarm"]
        assert np.array_equal(s.plan_copy().T_base_cam, own["T_base_cam_mm"])  # the plan on disk
        assert s.plan_not_ready() is None
    finally:
        s.shutdown()
    s2 = _restart(home)
    try:
        assert not _alerts(s2, "plan_changed_outside")
    finally:
        s2.shutdown()


def test_without_an_audit_row_the_mac_decides(tmp_path):
    """A plan file copied into a folder whose audit log never saw it: an edit with a recomputed
    hash fails this machine's MAC; it is kept aside and nothing is restored."""
    own = _saved_plan(tmp_path / "a")
    d = json.loads(json.dumps(own))
    _target_moved(d)
    _rehash(d)
    home = tmp_path / "b"
    home.mkdir()
    (home / "plan.json").write_text(json.dumps(d))
    s = _restart(home)
    try:
        al = _alerts(s, "plan_changed_outside")
        assert al and "MAC" in al[0].message and "starting empty" in al[0].message
        assert s.snapshot().fiducials == () and s.plan_copy().target_lps_mm is None
        assert len(list(home.glob("plan.changed-outside-*.json"))) == 1
    finally:
        s.shutdown()
    # the untouched file, copied the same way, is this machine's: restored without an alarm
    home2 = tmp_path / "c"
    home2.mkdir()
    (home2 / "plan.json").write_text(json.dumps(own))
    s = _restart(home2)
    try:
        assert not _alerts(s, "plan_changed_outside") and s.plan_copy().to_dict() == own
    finally:
        s.shutdown()


def test_plan_unreadable_stays_an_active_alarm_until_a_new_plan_is_saved(tmp_path):
    home = tmp_path / "home"
    _saved_plan(home)
    (home / "plan.json").write_text("{ not json")
    s = _restart(home)
    try:
        s.advance(5.0)
        active = [a for a in s.snapshot().alarms if a.code == "plan_unreadable"]
        assert active and "kept as plan.unreadable-" in active[0].message
        plan_sample(s)  # the operator makes (and saves) a new plan
        assert "plan_unreadable" not in [a.code for a in s.snapshot().alarms]
    finally:
        s.shutdown()
