"""Restart after a crash: the page shows the restored plan and a DISARMED robot."""

from __future__ import annotations

import numpy as np

from monotracker.sim.phantom import default_phantom


def test_restart_restores_plan_and_shows_disarmed(tmp_path, port):
    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp
    from monotracker.ui.status import status_html

    ph = default_phantom()
    s1 = Session(SessionConfig(home=tmp_path, arm_pin="2468"))
    for c in ph.fiducial_centres_lps[:5]:
        assert s1.add_fiducial(c).ok
    assert s1.confirm_fiducials().ok
    assert s1.set_entry(ph.sample_entry_lps).ok and s1.set_target(ph.sample_target_lps).ok
    assert s1.arm("2468").ok or True  # armed or not, a crash must come back disarmed
    s1._folder_lock.release()  # a crash: no shutdown; the OS drops a dead process's folder lock
    del s1

    s2 = Session(SessionConfig(home=tmp_path, arm_pin="2468"))
    try:
        app = MonoTrackerApp(s2, "127.0.0.1", port)
        snap = s2.snapshot()
        assert snap.robot.state == "disarmed"
        assert np.allclose(snap.plan.target_lps_mm, ph.sample_target_lps)
        assert app.notice and "restored" in app.notice and "DISARMED" in app.notice
        html = status_html(snap, notice=app.notice)
        assert "DISARMED" in html and "restored" in html
        app.server.stop()
    finally:
        s2.shutdown()


def test_status_banner_words_and_alerts():
    from types import SimpleNamespace as NS

    from monotracker.ui.status import STATE_STYLE, state_html, status_html

    for state, (_, word, _) in STATE_STYLE.items():
        snap = NS(robot=NS(state=state, connected=True), step="robot", alerts=(),
                  camera=NS(error=None, running=True, source="sim", fps=30.0), pose=None)
        html = state_html(snap)
        assert word in html and f"data-state='{state}'" in html
    ev = NS(level="alarm", t=1000.0, code="camera_freeze", message="camera <frozen>")
    snap = NS(robot=NS(state="holding", connected=False), step="robot", alerts=(ev,),
              camera=NS(error="unplugged", running=False, source="device:0", fps=0.0), pose=None)
    html = status_html(snap, now_wall=1005.0)
    assert "ALARM" in html and "camera &lt;frozen&gt;" in html and "unplugged" in html
    assert "NOT CONNECTED" in state_html(snap)
    assert "ALARM" not in status_html(snap, now_wall=2000.0)  # old alerts leave the banner


def test_active_alarms_all_listed_with_start_time_until_they_clear():
    """Every active alarm is listed (not only the newest), most important first as the engine
    orders them, each with the wall time it began; a recent alert already listed is not repeated."""
    import time as _time
    from types import SimpleNamespace as NS

    from monotracker.ui.status import status_html

    occl = NS(code="occlusion", level="alarm", priority=3, message="fiducials hidden", since=100.0, count=1)
    overrun = NS(code="loop_overrun", level="warning", priority=20, message="control loop overran", since=130.0, count=4)
    ev = NS(level="alarm", t=1000.0, code="occlusion", message="fiducials hidden")
    snap = NS(robot=NS(state="holding", connected=True), step="robot", alerts=(ev,), alarms=(occl, overrun),
              camera=NS(error=None, running=True, source="sim", fps=30.0), pose=None)
    wall0 = _time.mktime((2026, 1, 2, 10, 0, 0, 0, 0, -1))
    html = status_html(snap, now_wall=1001.0, wall_of=lambda t: wall0 + t)
    assert html.index("data-code='occlusion'") < html.index("data-code='loop_overrun'")
    assert "since 10:01:40" in html and "since 10:02:10 (x4)" in html
    assert "id='mt-alert'" not in html  # the newest alert is the listed occlusion: not shown twice
    cleared = NS(**{**vars(snap), "alarms": (overrun,)})
    assert "data-code='occlusion'" in status_html(cleared, now_wall=1001.0)  # still a recent alert
    assert "occlusion" not in status_html(cleared, now_wall=2000.0)
