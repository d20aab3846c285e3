"""Two browser tabs on one session (headless Chromium): one operator in control.

Checked against the session's own state and each page's DOM: the PIN is typed on a pad that
shows dots and exists only in the typing tab; a tab that is not in control cannot change the
session, switch the other tab's step, overwrite its fields or its result line; its STOP works.
Click-to-pick on the head sets the entry on the skin and the target inside the head.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from browser_helpers import (T_PAGE_MS, T_STATE, _click, _command, _input, _msg, _pin_pad, _seq, _take_control,
                             _wait, drawn, open_page, served_locked_sample)
pytestmark = pytest.mark.timeout(1800)  # the whole two-tab flow took > 900 s at load 25-30 on 2 cores (each wait is on state)


@pytest.fixture
def served_ct(tmp_path, monkeypatch, port):
    """A session with the sample CT loaded and its fiducials locked (the local operator did it).
    Its camera is the twin at the level of detected points (``camera="sim-points"``): these tests
    check who may do what from which tab, and arming needs only a fresh trusted pose, not a
    rendered image. With the rendered camera (``"sim"``: 30 frames a second drawn, detected and
    streamed to both tabs) each PIN-pad digit of the arming step waited on the page for seconds on
    2 cores (issue 35: the arming PIN took 29 s of the test's 80 s measured alone);
    tests/ui/test_e2e.py drives the rendered camera through the page."""
    with served_locked_sample(tmp_path, monkeypatch, port, {"camera": "sim-points"}) as served:
        yield served


def _open(browser, app, size=(1600, 1000)):
    page = open_page(browser, app, size)
    page.get_by_role("button", name="1 CT", exact=True).first.wait_for()
    return page


def _count_renders(view) -> list:
    """Count the render thread's updates of ``view`` (its ``render`` wrapped on the instance):
    ``[n]``, n growing by one per tick that brought this tab up to date."""
    n = [0]
    orig = view.render

    def render(snap):
        orig(snap)
        n[0] += 1

    view.render = render
    return n


def _settled(page, view, renders: list, ticks: int = 2) -> None:
    """Wait until the render thread has brought ``view``'s tab up to date ``ticks`` more times,
    viser has handed all it queued for the tab to its connection, and the page has drawn two
    more frames: whatever another tab's action made the server send this tab is on its page
    (state, not a wall-clock guess)."""
    from monotracker.ui.viser_threads import tab_caught_up

    n0 = renders[0]
    _wait(lambda: renders[0] >= n0 + ticks, what=f"{ticks} render ticks")
    _wait(lambda: tab_caught_up(view.client), what="the tab caught up")
    drawn(page)


def _visible_step(page) -> str:
    for k, title in (("ct", "Step 1: CT"), ("plan", "Step 2: plan"), ("register", "Step 3: register"), ("robot", "Step 4: robot")):
        if page.get_by_text(title).first.is_visible():
            return k
    return "?"


def test_second_tab_cannot_see_the_pin_nor_drive_but_can_stop(served_ct, browser):
    s, app = served_ct
    a = _open(browser, app)
    b = _open(browser, app)
    _wait(lambda: len(app.views()) == 2, what="two tabs")
    assert "VIEWING: nobody" in a.locator("#mt-control").inner_text()

    # tab A types the PIN on its pad: dots in A, nothing at all in B, never the digits
    _click(a, "Take control (PIN)")
    a.locator("#mt-pin-dots").wait_for()
    for k, d in enumerate("246", start=1):
        _click(a, d)
        a.wait_for_function(f"Number(document.querySelector('#mt-pin-dots').dataset.n) === {k}")
    assert a.locator("#mt-pin-dots").inner_text().count("\u25cf") == 3
    assert "246" not in a.locator("#mt-pin-dots").inner_text()
    assert b.locator("#mt-pin-dots").count() == 0 and "246" not in b.locator("body").inner_text()
    _click(a, "8")
    a.wait_for_function("Number(document.querySelector('#mt-pin-dots').dataset.n) === 4")
    assert "in control" in _command(a, "OK")
    _wait(lambda: s.snapshot().control.controller is not None, what="A in control")
    a_id = s.snapshot().control.controller
    view_a = next(v for v in app.views() if v.client_id == a_id)
    view_b = next(v for v in app.views() if v.client_id != a_id)
    renders_a = _count_renders(view_a)
    a.wait_for_function("document.querySelector('#mt-control').dataset.mine === '1'")
    b.wait_for_function("document.querySelector('#mt-control').innerText.includes('VIEWING')")
    assert "is in control" in b.locator("#mt-control").inner_text()
    assert "2468" not in a.locator("body").inner_text() and "2468" not in b.locator("body").inner_text()

    # A works in step 2; B looks at step 3: neither switches the other
    _click(a, "2 Plan")
    _wait(lambda: _visible_step(a) == "plan", what="A on Plan")
    _click(b, "3 Register")
    _wait(lambda: _visible_step(b) == "register", what="B on Register")
    _settled(a, view_a, renders_a)  # render ticks after B's switch: A must still show its own step
    assert view_a.step == "plan" and _visible_step(a) == "plan"

    # B's fields are B's: typing a target in B does not change A's field
    a_target = [_input(a, "Target (LPS mm)").input_value()]
    _click(b, "2 Plan")
    _wait(lambda: _visible_step(b) == "plan", what="B on Plan")
    boxes_b = b.locator("xpath=//label[normalize-space()='Target (LPS mm)']/../../following-sibling::div[1]//input")
    boxes_b.nth(0).fill("99.5")
    boxes_b.nth(0).press("Tab")
    _wait(lambda: view_b.steps["plan"].h_target.value[0] == 99.5, what="B's typed target on the server")
    _settled(a, view_a, renders_a)
    assert view_a.steps["plan"].h_target.value[0] != 99.5
    assert [_input(a, "Target (LPS mm)").input_value()] == a_target

    # B cannot drive: its command is refused on B's result line only, the session unchanged
    seq_a = _seq(a)
    msg = _command(b, "Use the sample plan")
    assert "another station is in control" in msg and b.locator("#mt-msg").last.get_attribute("data-ok") == "0"
    assert not s.snapshot().plan.complete
    assert _seq(a) == seq_a and "another station" not in _msg(a)
    # a wrong PIN from B does not take control
    _click(b, "Take control (PIN)")
    assert "wrong PIN" in _pin_pad(b, "1111")
    assert s.snapshot().control.controller == a_id

    # A drives (sample plan), B sees the result in the session, not A's result line
    assert "Sample plan" in _command(a, "Use the sample plan")
    _wait(lambda: s.snapshot().plan.complete, what="plan")
    assert "Sample plan" not in _msg(b)

    # arming needs a fresh trusted pose for this plan: the local operator starts the camera
    assert s.start_camera().ok
    _wait(lambda: s.snapshot().pose is not None and s.snapshot().pose.trusted, what="trusted pose")
    # A arms; B's STOP works, always
    _click(a, "4 Robot")
    _wait(lambda: _visible_step(a) == "robot", what="A on Robot")
    # the point-level twin carries the image detector's 0.15 px noise, so the trust gate may
    # refuse a stretch of frames (the 2 mm tail rule near its 0.1 % limit: once in a suite run,
    # "probability 0.11 % > 0.1 %"); Arm is then refused, as it must be, and the operator presses
    # it again once the pose is trusted. This test is about the tabs, not the gate.
    for _ in range(5):
        _click(a, "Arm (PIN)")
        res = _pin_pad(a, "2468")
        if "no trusted, fresh pose" not in res:
            break
        _wait(lambda: s.snapshot().pose is not None and s.snapshot().pose.trusted, what="trusted pose")
    assert "Arm" in res and "no trusted, fresh pose" not in res, res
    _wait(lambda: s.snapshot().robot.state == "armed", what=f"armed ({_msg(a)})")
    _click(b, "STOP")
    _wait(lambda: s.snapshot().robot.state == "estopped", what="estop from the viewing tab")
    b.wait_for_function("document.querySelector('#mt-robot-state').dataset.state === 'estopped'")
    a.wait_for_function("document.querySelector('#mt-robot-state').dataset.state === 'estopped'")
    # ...and B cannot reset it
    _click(b, "4 Robot")
    _wait(lambda: _visible_step(b) == "robot", what="B on Robot")
    assert "another station is in control" in _command(b, "Reset e-stop")
    assert s.snapshot().robot.state == "estopped"

    # A closes: its control ends with it
    a.close()
    _wait(lambda: s.snapshot().control.controller is None, what="control released on disconnect")
    b.close()


def _canvas_centre(page):
    """The centre of the 3D view between the docked panels (px)."""
    boxes = [c.bounding_box() for c in page.locator("canvas").all()]
    box = max((bb for bb in boxes if bb), key=lambda bb: bb["width"] * bb["height"])
    left = page.locator("#mt-robot-state").bounding_box()
    right = page.get_by_text("Step 2: plan").first.bounding_box()
    x0 = max(box["x"], left["x"] + left["width"] + 10)
    x1 = min(box["x"] + box["width"], right["x"] - 10)
    return (x0 + x1) / 2, box["y"] + box["height"] / 2


def test_click_on_head_sets_entry_on_skin_and_target_inside(served_ct, browser):
    s, app = served_ct
    page = _open(browser, app)
    assert "in control" in _take_control(page, "2468")
    _click(page, "2 Plan")
    _wait(lambda: _visible_step(page) == "plan", what="Plan")
    # the selector shows "set entry" and a click does exactly that
    assert _input(page, "Head click sets").input_value() == "set entry"
    mesh = s.snapshot().head_mesh
    verts = np.asarray(mesh.vertices)
    x, y = _canvas_centre(page)
    t0 = time.monotonic()
    while s.snapshot().plan.entry_lps_mm is None:  # the first clicks may land before the mesh is drawn
        assert time.monotonic() - t0 < T_STATE, f"no entry from a click on the head (last: {_msg(page)})"
        before = _seq(page)
        page.mouse.click(x, y)
        try:
            page.wait_for_function(f"Number(document.querySelector('#mt-msg').dataset.seq) > {before}", timeout=5000)
        except Exception:  # noqa: BLE001 - the click did not reach the head yet: try again
            pass
    entry = np.asarray(s.snapshot().plan.entry_lps_mm)
    assert np.min(np.linalg.norm(verts - entry, axis=1)) < 3.0, "the entry lies on the skin surface"
    assert "Traceback" not in page.content() and "rtree" not in _msg(page)

    # "set target": the point halfway through the head under the pointer, deep inside
    _input(page, "Head click sets").click()
    page.get_by_role("option", name="set target").click()
    _wait(lambda: app.views()[0].steps["plan"].h_click.value == "set target", what="set target mode")
    before = _seq(page)
    page.mouse.click(x, y)
    page.wait_for_function(f"Number(document.querySelector('#mt-msg').dataset.seq) > {before}")
    _wait(lambda: s.snapshot().plan.target_lps_mm is not None, what=f"target from a click ({_msg(page)})")
    target = np.asarray(s.snapshot().plan.target_lps_mm)
    assert np.min(np.linalg.norm(verts - target, axis=1)) > 20.0, "the target lies deep inside, not on the skin"
    assert np.all(target > verts.min(axis=0)) and np.all(target < verts.max(axis=0))

    # the Slicer export reaches the browser as a download (and the engine's files on the server)
    with page.expect_download(timeout=T_PAGE_MS) as dl:
        _click(page, "Export to 3D Slicer (.mrk.json)")
    name = dl.value.suggested_filename
    assert name.endswith(".zip") or name.endswith(".mrk.json")
    data = Path(dl.value.path()).read_bytes()
    assert len(data) > 100
    written = sorted((s.home / "slicer").glob("*.mrk.json"))
    assert written, "the engine wrote the markups"
    if name.endswith(".zip"):
        import io
        import zipfile

        assert sorted(zipfile.ZipFile(io.BytesIO(data)).namelist()) == sorted(p.name for p in written)
    page.close()
