"""``Session.set_ball_finish``: the finish of this patient's kit's balls, stated by the OR team,
kept in the plan (and a restored plan), audited, refused while the arm is engaged, and applied by
the camera when it starts (vision's ``TrackerConfig.ball_finish``: glossy balls beside their
contact shadows need the wider few-ball cover). Truth: what was set, the plan file on disk, the
tracker the camera rig built."""

from __future__ import annotations

import json

from monotracker.engine import Session, SessionConfig
from monotracker.engine.plan import load_plan

from .conftest import plan_sample
from .conftest import restart as _restart
from .conftest import saved_plan as _saved_plan


def test_the_finish_is_kept_in_the_plan_audited_and_restored(home):
    s = Session(SessionConfig(home=home, clock="sim"))
    try:
        snap = s.snapshot()
        assert snap.ball_finish is None and snap.ball_finish_default == "read"
        for bad in ("shiny", "", "Glossy", 3, True, ["glossy"]):
            r = s.set_ball_finish(bad)
            assert not r.ok and r.message and "\n" not in r.message and "ball finish" in r.message, bad
        assert s.plan_copy().ball_finish is None
        r = s.set_ball_finish("glossy")
        assert r.ok and "glossy" in r.message, r.message
        assert s.snapshot().ball_finish == "glossy"
        assert load_plan(home / "plan.json").ball_finish == "glossy"
        rows = s.audit_entries(code="ball_finish_set")
        assert rows and rows[-1].data == {"finish": "glossy", "previous": None}
    finally:
        s.shutdown()
    s2 = Session(SessionConfig(home=home, clock="sim", ball_finish="matte"))   # survives a restart
    try:
        assert s2.snapshot().ball_finish == "glossy" and s2.snapshot().ball_finish_default == "matte"
        assert s2.config.frame_rules(s2.plan_copy().ball_finish).ball_finish == "glossy"   # the plan's wins
        assert s2.set_ball_finish(None).ok                                  # back to the launch setting
        assert s2.snapshot().ball_finish is None
        assert s2.config.frame_rules(s2.plan_copy().ball_finish).ball_finish == "matte"
    finally:
        s2.shutdown()


def test_a_bad_finish_in_a_restored_plan_is_left_out(home):
    """A plan file edited outside the app with a word vision does not know: the rest of the plan
    is restored, the finish falls back to the launch setting, and the field is named."""
    d = _saved_plan(home)
    assert d["ball_finish"] is None
    d["ball_finish"] = "shiny"
    s = _restart(home, d)
    try:
        assert s.plan_copy().ball_finish is None and len(s.plan_copy().fiducials) == len(d["fiducials"])
        said = " ".join(a.message for a in s.snapshot().alerts)
        assert "ball_finish" in said, said
    finally:
        s.shutdown()


def test_refused_while_the_arm_is_engaged(home):
    _saved_plan(home)
    s = _restart(home)
    try:
        assert s.set_ball_finish("matte").ok
        assert s.start_camera().ok
        s.advance(0.3)
        assert s.arm("1234").ok
        r = s.set_ball_finish("glossy")
        assert not r.ok and "disarm" in r.message, r.message
        assert s.plan_copy().ball_finish == "matte"
        assert s.disarm().ok
        assert s.snapshot().pose is not None
        r = s.set_ball_finish("glossy")
        assert r.ok and "camera restarted" in r.message, r.message   # the pose judged by the old rules goes
        assert s.audit_entries(code="camera_stopped") and s._loop.camera.rig.running and s.snapshot().pose is None
    finally:
        s.shutdown()
    assert json.loads((home / "plan.json").read_text())["ball_finish"] == "glossy"


def test_the_camera_applies_the_plans_finish_when_it_starts(home):
    s = Session(SessionConfig(home=home, clock="sim", camera="sim"))
    try:
        plan_sample(s)
        assert s.set_ball_finish("glossy").ok
        assert s.start_camera().ok
        assert s._loop.camera.rig.tracker.config.ball_finish == "glossy"
        assert s.set_ball_finish("matte").ok                   # the running camera restarts with it
        assert s._loop.camera.rig.running and s._loop.camera.rig.tracker.config.ball_finish == "matte"
        assert s.stop_camera().ok
        assert s.set_ball_finish(None).ok                      # the launch setting
        assert s.start_camera().ok
        assert s._loop.camera.rig.tracker.config.ball_finish == "read"
    finally:
        s.shutdown()
