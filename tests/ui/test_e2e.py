"""End-to-end: the whole workflow in headless Chromium against a real engine session
(simulated camera and UR10), checked against the session's own state (independent of the page).

Screenshots of each step go to test-artifacts/ui/.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from browser_helpers import (APP_OPTIONS, T_STATE, _click, _command, _input, _msg, _pin_pad, _state, _take_control,
                             _wait, drawn, open_page)

pytestmark = [pytest.mark.timeout(900), pytest.mark.alone]


@pytest.fixture
def served(tmp_path, monkeypatch, port):
    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp

    monkeypatch.setenv("MONOTRACKER_HOME", str(tmp_path))
    # the engine's own limits (a trusted pose older than 0.15 s holds the arm, a camera silent for
    # 0.1 s is frozen) and a breathing head, and the arm must reach the entry while tracking. The
    # pose pipeline and the simulated camera run at normal priority, never above the web server
    # (engine/pipeline_priority.py: STOP outranks them); Start is sent right after a pose arrived
    # (engine/loop/robot.START_ARRIVAL_S) and every wait below is on state. Beside 4 CPU hogs
    # (MONOTRACKER_TEST_HOGS=4, tests/conftest.py) with a software-rendered browser taking its
    # share, the camera runs late and no trusted pose comes (issue 33, open). The pose ages as the
    # engine sees them arrive are printed at each step.
    s = Session(SessionConfig(home=tmp_path, camera="sim", trajectory="breathing", robot="sim", arm_pin="2468"))
    ages = _record_pose_ages(s)
    s.start()
    app = MonoTrackerApp(s, "127.0.0.1", port, **APP_OPTIONS)  # the camera and pipeline at 30 fps
    app.start()
    yield s, app, ages
    app.stop()
    s.shutdown()


def _record_pose_ages(s) -> list:
    """Measure only: ``(now, age_s)`` of every estimate as the engine sees it arrive (capture ->
    engine, s), so that a failure says how old the poses were against the limit."""
    ages: list = []
    orig = s._loop.on_pose

    def on_pose(sample, now):
        ages.append((now, now - sample.t_capture))
        orig(sample, now)

    s._loop.on_pose = on_pose
    return ages


def _pose_age_report(s, ages: list) -> str:
    """One line: the pose age at arrival (ms) against the session's limit, the gaps between
    arrivals, the stale/frozen holds so far and the load."""
    rows = list(ages)
    if not rows:
        return "no pose arrived"
    age = 1000 * np.array([a for _, a in rows])
    gaps = 1000 * np.diff([n for n, _ in rows]) if len(rows) > 1 else np.zeros(1)
    lim = 1000 * s.config.max_pose_age_s
    return (f"{len(rows)} poses, age at arrival p50/p95/p99/max {np.percentile(age, 50):.0f}/"
            f"{np.percentile(age, 95):.0f}/{np.percentile(age, 99):.0f}/{age.max():.0f} ms, "
            f"{100 * np.mean(age > lim):.1f}% over the {lim:.0f} ms limit; arrival gap p95/max "
            f"{np.percentile(gaps, 95):.0f}/{gaps.max():.0f} ms; holds: "
            f"{len(s.audit_entries(code='pose_stale'))} pose_stale, {len(s.audit_entries(code='camera_freeze'))} "
            f"camera_freeze; load {os.getloadavg()[0]:.1f}")


def test_whole_workflow_in_browser(served, browser, artifacts):
    s, app, ages = served
    t_start = time.monotonic()
    page = open_page(browser, app)
    page.get_by_role("button", name="Load sample CT").wait_for()
    assert _state(page) == "disarmed"
    # a tab views until it takes control with the PIN
    assert "VIEWING" in page.locator("#mt-control").inner_text()
    assert "in control" in _take_control(page, "2468")
    page.wait_for_function("document.querySelector('#mt-control').dataset.mine === '1'")

    # ---- step 1: CT. Bad input first: a wrong path gives a message, not a traceback.
    _input(page, "CT file or folder").fill("/no/such/ct.nii.gz")
    assert "no such file" in _command(page, "Open CT")
    assert page.locator("#mt-msg").last.get_attribute("data-ok") == "0"
    assert "Traceback" not in page.content()
    msg = _command(page, "Lock fiducials and go to Plan")  # nothing goes on before a CT is confirmed
    assert "Lock fiducials" in msg and "needed" in msg and not s.snapshot().fiducials_locked

    _click(page, "Load sample CT")
    _wait(lambda: len(s.snapshot().fiducials) == 9 and s.snapshot().head_mesh is not None, what="sample CT")
    page.locator("#mt-fiducials").wait_for()
    page.wait_for_function("document.querySelectorAll('#mt-fiducials tr').length === 10")
    # reject one fiducial, then undo it, confirm the rest
    _input(page, "Fiducial number").fill("3")
    _input(page, "Fiducial number").press("Enter")
    _click(page, "Reject")
    _wait(lambda: s.snapshot().fiducials[3].status == "rejected", what="reject")
    _click(page, "Undo")
    _wait(lambda: s.snapshot().fiducials[3].status == "detected", what="undo")
    _click(page, "Confirm all detected")
    _wait(lambda: all(f.status == "confirmed" for f in s.snapshot().fiducials), what="confirm all")
    drawn(page)
    page.screenshot(path=str(artifacts / "1_ct.png"))
    _click(page, "Lock fiducials and go to Plan")
    _wait(lambda: s.snapshot().fiducials_locked, what="lock")

    print(f"[{time.monotonic() - t_start:5.1f} s] ---- step 2")
    # ---- step 2: plan (typed target + sample entry)
    page.get_by_role("button", name="Set entry").wait_for()
    _click(page, "Use the sample plan")
    _wait(lambda: s.snapshot().plan.complete, what="plan")
    page.locator("#mt-plan-metrics").wait_for()
    # type a target 3 mm further right (-x) and set it: the page shows the new length
    new_target = np.asarray(s.snapshot().plan.target_lps_mm) + [-3.0, 0.0, 0.0]
    boxes = page.locator("xpath=//label[normalize-space()='Target (LPS mm)']/../../following-sibling::div[1]//input")
    for k in range(3):
        boxes.nth(k).fill(f"{new_target[k]:.2f}")
        boxes.nth(k).press("Tab")
    # the typed value reaches the server asynchronously: press "Set target" until the session has
    # it (each press waits for its own result line)
    t0 = time.monotonic()
    while not np.allclose(s.snapshot().plan.target_lps_mm, np.round(new_target, 2), atol=0.01):
        assert time.monotonic() - t0 < T_STATE, "timed out waiting for the typed target"
        _command(page, "Set target")
    length = s.snapshot().plan.path_length_mm
    page.wait_for_function(f"document.querySelector('#mt-plan-metrics').innerText.includes('Length {length:.1f} mm')")
    drawn(page)
    page.screenshot(path=str(artifacts / "2_plan.png"))
    _click(page, "Path is good: go to Register")

    print(f"[{time.monotonic() - t_start:5.1f} s] ---- step 3")
    # ---- step 3: register with the simulated camera
    _click(page, "Start camera")
    too_slow = _registered(page, s, ages)
    if too_slow:
        page.close()
        pytest.xfail(too_slow)     # no trusted pose for the steps after: the engine refused, as it must
    drawn(page)
    page.screenshot(path=str(artifacts / "3_register.png"))

    print(f"[{time.monotonic() - t_start:5.1f} s] ---- step 4")
    # ---- step 4: robot. Wrong PIN refused, right PIN arms.
    _click(page, "4 Robot")
    _click(page, "Arm (PIN)")
    assert "wrong PIN" in _pin_pad(page, "0000")
    assert s.snapshot().robot.state == "disarmed"
    # arming needs a fresh trusted pose too: a refusal says why in the page and the operator
    # arms again (the right PIN is no wrong try), each press waiting for its own result
    t0 = time.monotonic()
    while s.snapshot().robot.state != "armed":
        assert time.monotonic() - t0 < T_STATE, f"timed out waiting for arming (last: {_msg(page)})"
        _click(page, "Arm (PIN)")
        msg = _pin_pad(page, "2468")
        if s.snapshot().robot.state != "armed":
            print("arming refused:", msg)
            assert "no trusted, fresh pose" in msg and page.locator("#mt-msg").last.get_attribute("data-ok") == "0"
            _wait(lambda: s.snapshot().pose is not None and s.snapshot().pose.trusted, what="trusted pose again")
    print(f"[{time.monotonic() - t_start:5.1f} s] armed; {_pose_age_report(s, ages)}")
    page.wait_for_function("document.querySelector('#mt-robot-state').dataset.state === 'armed'")
    # tracking needs a fresh trusted pose; on a loaded machine a start can be refused ("pose is
    # stale", with the reason in the page): the operator presses again, as the test does, each
    # press waiting for its own result, until the session tracks (or the generous limit)
    t0 = time.monotonic()
    while s.snapshot().robot.state not in ("tracking", "holding"):
        assert time.monotonic() - t0 < T_STATE, f"timed out waiting for tracking (last: {_msg(page)})"
        msg = _command(page, "Start tracking")
        if s.snapshot().robot.state not in ("tracking", "holding"):
            print("start refused:", msg)
            assert "Start tracking" in msg and page.locator("#mt-msg").last.get_attribute("data-ok") == "0"
            _wait(lambda: s.snapshot().pose is not None and s.snapshot().pose.trusted, what="trusted pose again")
    page.wait_for_function("['tracking','holding'].includes(document.querySelector('#mt-robot-state').dataset.state)")
    print(f"[{time.monotonic() - t_start:5.1f} s] tracking started; {_pose_age_report(s, ages)}")
    # the arm follows the breathing head onto the entry (the robot's truth, not the page): poses
    # arriving older than max_pose_age_s keep it holding short of it, and that is what the
    # engine must do on a machine too slow for the pipeline beside the browser (see below)
    too_slow = _tip_on_the_entry(s, ages)
    print(f"[{time.monotonic() - t_start:5.1f} s] tracking: "
          f"{too_slow or 'tip on the entry'}; {_pose_age_report(s, ages)}")
    drawn(page)
    page.screenshot(path=str(artifacts / "4_robot_tracking.png"))

    print(f"[{time.monotonic() - t_start:5.1f} s] occlusion:")
    # occlusion: hide the fiducials (simulated fault) -> alert in the page, arm holds
    _click(page, "3 Register")
    _input(page, "Simulate a fault (sim only)").click()
    page.get_by_role("option", name="occlude-all").click()
    _click(page, "Inject fault")
    # the state, not the newest alert (other warnings may follow it at once on a loaded machine)
    _wait(lambda: s.snapshot().robot.state == "holding" and s.snapshot().pose is not None
          and not s.snapshot().pose.trusted, what="holding on occlusion")
    page.locator("#mt-occlusion").wait_for()
    # the always-visible panel lists the active condition (not only the newest alert) until it clears
    _wait(lambda: any(a.code in ("occlusion", "pose_lost") for a in s.snapshot().alarms), what="occlusion alarm")
    page.wait_for_function("[...document.querySelectorAll('#mt-alarms li')].some(l => "
                           "['occlusion', 'pose_lost'].includes(l.dataset.code))")
    drawn(page)
    page.screenshot(path=str(artifacts / "5_occlusion.png"))

    print(f"[{time.monotonic() - t_start:5.1f} s] stop tracking,")
    # stop tracking, then the big STOP button latches the e-stop
    _click(page, "4 Robot")
    _click(page, "Stop tracking")
    _wait(lambda: s.snapshot().robot.state == "armed", what="stopped tracking")
    _click(page, "STOP")
    _wait(lambda: s.snapshot().robot.state == "estopped", what="estop")
    page.wait_for_function("document.querySelector('#mt-robot-state').dataset.state === 'estopped'")
    page.screenshot(path=str(artifacts / "6_estop.png"))
    assert "Traceback" not in page.content()
    print(f"e2e workflow took {time.monotonic() - t_start:.0f} s; {_pose_age_report(s, ages)}")
    page.close()
    if too_slow:
        pytest.xfail(too_slow)


#: the share of poses arriving over the engine's age limit above which a machine counts as too
#: slow for the pose pipeline beside a software-rendered browser (quiet machines: 3-8 %)
TOO_SLOW_SHARE = 0.08


def _tip_on_the_entry(s, ages: list) -> str:
    """Wait until the arm tracks with its tip on the entry (< 2 mm): "" when it does. On a 2-core
    machine the simulated camera, the pose pipeline and chromium drawing the 3D view in software
    need about the whole machine, and where they do not fit, poses arrive over the 150 ms limit,
    the engine holds (the resume dwell doubles to 1.2 s when the stream fails again) and the arm
    stays short of the entry: the right answer there (docs/performance.md, "The end-to-end test
    on a machine too slow"). Then this returns why, once it has checked that the engine held for
    freshness and said so, with over TOO_SLOW_SHARE of the poses late on arrival; anything else
    (fresh poses and no reach, no hold for freshness recorded) fails. The rest of the workflow
    runs either way; the test then ends as an expected failure that names the measured lateness."""
    try:
        _wait(lambda: s.snapshot().robot.state == "tracking" and (s.snapshot().robot.tip_error_mm or 1e9) < 2.0,
              what="the tip on the entry while tracking")
        return ""
    except AssertionError:
        pass        # not within T_STATE: say why below, or fail
    snap = s.snapshot()
    report = (f"the arm did not reach the entry in {T_STATE:.0f} s (last: {snap.robot.state}, "
              f"{snap.robot.tip_error_mm} mm; pose {snap.pose}; {_pose_age_report(s, ages)})")
    assert snap.robot.state in ("holding", "tracking"), report
    late = _late_share_held(s, ages, report)
    return (f"this machine is too slow for the pose pipeline beside a software-rendered browser: "
            f"{100 * late:.0f} % of the poses arrived over the {1000 * s.config.max_pose_age_s:.0f} ms limit "
            f"and the engine held the arm {snap.robot.tip_error_mm:.0f} mm short of the entry, as it must")


def _registered(page, s, ages: list) -> str:
    """Wait until the session trusts a pose and the page shows POSE VALID: "" when it does. Beside
    CPU hogs the same machine can be too slow for that within T_STATE: poses arrive over the age
    limit and the engine keeps them untrusted (or trusts them in spells too short for the page's
    next push). Then this returns why, with the same proof as :func:`_tip_on_the_entry` (over
    TOO_SLOW_SHARE of the poses late on arrival and the engine said so); anything else fails."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        _wait(lambda: s.snapshot().pose is not None and s.snapshot().pose.trusted,
              what=lambda: f"trusted pose (last: {s.snapshot().pose})")
        page.wait_for_function("document.querySelector('#mt-pose-banner') && "
                               "document.querySelector('#mt-pose-banner').innerText.includes('POSE VALID')",
                               timeout=1000 * T_STATE)
        return ""
    except (AssertionError, PlaywrightTimeout):
        pass        # not within T_STATE: say why below, or fail
    snap = s.snapshot()
    banner = page.locator("#mt-pose-banner").inner_text() if page.locator("#mt-pose-banner").count() else "(none)"
    report = (f"no trusted pose shown in {T_STATE:.0f} s (pose {snap.pose}; the page: {banner!r}; "
              f"{_pose_age_report(s, ages)})")
    late = _late_share_held(s, ages, report)
    return (f"this machine is too slow for the pose pipeline beside a software-rendered browser: "
            f"{100 * late:.0f} % of the poses arrived over the {1000 * s.config.max_pose_age_s:.0f} ms limit "
            "and the engine kept the registration untrusted, as it must")


def _late_share_held(s, ages: list, report: str) -> float:
    """The share of poses that arrived over the engine's age limit, once it is checked to be over
    TOO_SLOW_SHARE and the engine recorded a hold for freshness (or its pose says stale / late);
    else the test fails with ``report``."""
    snap = s.snapshot()
    rows = list(ages)
    late = float(np.mean([a > s.config.max_pose_age_s for _, a in rows])) if rows else 0.0
    assert late > TOO_SLOW_SHARE, f"{report}: yet the poses came in fresh"
    freshness = [a for a in s.audit_entries() if getattr(a, "code", "") in ("pose_stale", "pipeline_overloaded",
                                                                            "camera_late")]
    assert freshness or (snap.pose is not None and ("stale" in snap.pose.reason or "late" in snap.pose.reason)), \
        f"{report}: and no hold for freshness was recorded"
    return late
