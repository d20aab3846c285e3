"""STOP works with a PIN pad (a modal) open (issue 34): a press at the STOP button's place on the
screen (a gloved finger does not look for Cancel first) and the Space / Escape keys each latch
the e-stop in the robot's control process, and the page shows E-STOPPED from it.

Checked against the session and the control process's own published state, waiting on state
only (it must hold with CPU hogs beside it: ``MONOTRACKER_TEST_HOGS=4``)."""

from __future__ import annotations

import pytest
from browser_helpers import APP_OPTIONS, T_STATE, _wait, open_page

pytestmark = pytest.mark.timeout(900)


@pytest.fixture
def served_robot(tmp_path, monkeypatch, port):
    """A real-clock session with the simulated UR10 connected (its control process running,
    disarmed), served on ``port``; no CT or camera needed to stop an arm."""
    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp

    monkeypatch.setenv("MONOTRACKER_HOME", str(tmp_path))
    s = Session(SessionConfig(home=tmp_path, robot="sim", arm_pin="2468", clock="real"))
    s.start()
    app = None
    try:
        assert s.connect_robot().ok
        _wait(lambda: s.snapshot().robot.state == "disarmed" and s.snapshot().robot.connected, what="robot connected")
        app = MonoTrackerApp(s, "127.0.0.1", port, **APP_OPTIONS)
        app.start()
        yield s, app
    finally:
        if app is not None:
            app.stop()
        s.shutdown()


def _controller_state(s) -> str:
    """The state the robot's control process itself published (shared memory)."""
    return s._loop.robot.rig.proc.state().state


def _open_pad(page) -> None:
    page.get_by_role("button", name="Take control (PIN)", exact=True).first.click()
    page.locator("#mt-pin-dots").first.wait_for(state="visible")


def _stop_centre(page):
    box = page.get_by_role("button", name="STOP", exact=True).first.bounding_box()
    return box["x"] + box["width"] / 2, box["y"] + box["height"] / 2


def _page_state_is(page, state: str) -> None:
    page.wait_for_function(f"document.querySelector('#mt-robot-state') && "
                           f"document.querySelector('#mt-robot-state').dataset.state === '{state}'")


def _reset(s, page) -> None:
    assert s.reset_estop().ok
    _wait(lambda: _controller_state(s) == "disarmed", what="reset")
    _page_state_is(page, "disarmed")


@pytest.mark.parametrize("press", ["click", "Escape", "Space"])
def test_stop_latches_with_the_pin_pad_open(served_robot, browser, press):
    s, app = served_robot
    page = open_page(browser, app)
    _page_state_is(page, "disarmed")
    _open_pad(page)
    x, y = _stop_centre(page)
    if press == "click":
        # nothing covers STOP: the element at its centre is the STOP button itself, not the
        # pad's overlay (a finger presses what is drawn there)
        on_top = page.evaluate("([x, y]) => { const b = document.elementFromPoint(x, y); "
                               "return !!b && !!b.closest('button') && b.closest('button').innerText.trim() }", [x, y])
        assert on_top == "STOP", f"the press at STOP's place lands on {on_top!r}"
        page.mouse.click(x, y)
    else:
        page.keyboard.press(press)
    _wait(lambda: s.snapshot().robot.state == "estopped", what=f"the e-stop after {press} with the PIN pad open")
    assert _controller_state(s) == "estopped"  # the control process latched it, not only the engine
    _page_state_is(page, "estopped")
    assert page.locator("#mt-pin-dots").first.is_visible()  # the pad stays; nothing was typed on it
    assert page.locator("#mt-pin-dots").first.get_attribute("data-n") == "0"
    # the pad still works after the stop, and a second STOP after a reset still latches
    page.get_by_role("button", name="Cancel", exact=True).last.click()
    page.locator("#mt-pin-dots").first.wait_for(state="detached")
    _reset(s, page)
    _open_pad(page)
    page.mouse.click(x, y)
    _wait(lambda: _controller_state(s) == "estopped", what="a second STOP with the pad open")
    _page_state_is(page, "estopped")
    page.close()


def test_every_stop_is_audited_with_the_controllers_confirmation(served_robot, browser):
    """The press is recorded (an ``estop`` alarm row saying the control process confirmed it),
    and the robot_state row carries the e-stop's own reason."""
    s, app = served_robot
    page = open_page(browser, app)
    _page_state_is(page, "disarmed")
    _open_pad(page)
    page.mouse.click(*_stop_centre(page))
    _wait(lambda: any("confirmed" in e.message for e in s.audit_entries(code="estop")), what="the estop row",
          timeout=T_STATE)

    def state_rows():
        return [e for e in s.audit_entries(code="robot_state") if e.session_id == s.session_id]

    _wait(lambda: any(e.data.get("to") == "estopped" for e in state_rows()), what="the robot_state row")
    last = state_rows()[-1].data
    assert (last["from"], last["to"], last["reason"]) == ("disarmed", "estopped", "operator e-stop")
    page.close()
