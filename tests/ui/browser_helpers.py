"""Helpers shared by the browser tests: waits on state (never on wall-clock guesses), clicks,
viser's inputs by label, the result line and its sequence number, the PIN pad."""

from __future__ import annotations

import time
from contextlib import contextmanager

#: the most animation frames a second a test page draws (issue 35). Without a GPU, chromium draws
#: the 3D view in software (SwiftShader): viser's client draws on demand, but every scene update
#: (the head moving with the breathing trajectory, the arm) opens a 250 ms window of 60 Hz frames,
#: so with the app's 8 Hz render thread the browser drew continuously and took most of a core
#: from the app under test on a 2-core machine (the end-to-end test's pose pipeline starved
#: beside it). The tests check the page's widgets, the session and where a click lands, not the
#: frame rate: each page's ``requestAnimationFrame`` is capped at this rate (an init script in its
#: own page world; Playwright's actionability checks run in their own world, unaffected), so the
#: scene still follows the session, up to 1/BROWSER_FPS s later. GUI-only updates (panels, result
#: lines, the state block) do not wait for a frame in viser's client (messageQueue.ts).
BROWSER_FPS = 5

# Every wait is on state (the session's or the page's) with a generous limit: on a loaded 2-core
# machine the same step can take 10x longer than on a quiet one, and that is not a bug.
T_STATE = 120.0  # s, session state
T_PAGE_MS = 120_000  # ms, the page catching up with the session
#: the live overlay's most frames a second in the browser tests (``MonoTrackerApp(max_stream_fps=)``,
#: 30 in the app; issue 35): each streamed frame is drawn and JPEG-encoded by the app and decoded
#: and composited in software by chromium, on the same 2 cores as the pose pipeline; on the live
#: steps each click of the end-to-end test took ~30 s at load 9. The tests check the workflow, not
#: the stream's rate (``benchmarks/web_overlay.py`` measures that).
STREAM_FPS = 5.0
#: ``MonoTrackerApp`` options of every browser test: the overlay at :data:`STREAM_FPS`, and no HDR
#: environment map (``environment_map=False``): headless chromium draws the 3D view in software,
#: and the map's prefiltering and shaders cost it ~10 of the ~14 CPU s of its GPU process at each
#: page load of the sample scene (issue 33: 4 CPU hogs beside the tests left the browser a
#: fraction of a core, and clicks waited for that first frame). The tests check the page's logic.
APP_OPTIONS = dict(max_stream_fps=STREAM_FPS, environment_map=False)


def _wait(pred, timeout=T_STATE, what="condition"):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        v = pred()
        if v:
            return v
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what() if callable(what) else what}")


def _click(page, name):
    page.get_by_role("button", name=name, exact=True).first.click()


def _input(page, label):
    """The input next to a viser label (viser's label 'for' does not match the input id)."""
    return page.locator(f"xpath=//label[normalize-space()='{label}']/../../following-sibling::div[1]//input").first


def _msg(page):
    return page.locator("#mt-msg").last.inner_text()


def _seq(page) -> int:
    """How many command results the page has shown (#mt-msg data-seq)."""
    return int(page.locator("#mt-msg").last.get_attribute("data-seq") or 0)


def _command(page, name, *, after: int | None = None) -> str:
    """Click a button and wait until the page shows the result of *this* click (a new data-seq)."""
    before = _seq(page) if after is None else after
    _click(page, name)
    page.wait_for_function(f"Number(document.querySelector('#mt-msg').dataset.seq) > {before}")
    return _msg(page)


def _pin_pad(page, pin: str) -> str:
    """Type ``pin`` on the open PIN pad (big buttons, dots shown) and press OK; the result line."""
    page.locator("#mt-pin-dots").wait_for()
    for d in pin:
        n = int(page.locator("#mt-pin-dots").get_attribute("data-n"))
        _click(page, d)
        page.wait_for_function(f"document.querySelector('#mt-pin-dots') && "
                               f"Number(document.querySelector('#mt-pin-dots').dataset.n) === {n + 1}")
    assert pin not in page.locator("#mt-pin-dots").inner_text()  # dots, never the digits
    return _command(page, "OK")


def _take_control(page, pin: str) -> str:
    _click(page, "Take control (PIN)")
    return _pin_pad(page, pin)


def _state(page):
    return page.locator("#mt-robot-state").first.get_attribute("data-state")


def drawn(page, frames: int = 2) -> None:
    """Wait until the page has drawn ``frames`` more animation frames (its ``requestAnimationFrame``,
    capped at :data:`BROWSER_FPS` in the tests: 0.2 s each there): what the page had received
    is then on screen, for a screenshot. A wait on the page's state, not a guess at how long
    drawing takes (the end-to-end test slept 1-1.5 s before each screenshot: 5.5 s in all)."""
    page.evaluate("n => new Promise(done => { let k = 0; "
                  "const tick = () => (++k >= n ? done() : requestAnimationFrame(tick)); "
                  "requestAnimationFrame(tick); })", frames)


def open_page(browser, app, size=(1600, 1000), ready: str = "#mt-control"):
    """A new tab of ``size`` (width, height px) on the app, once the element ``ready`` (a CSS
    selector) is there; every page wait in it has the generous :data:`T_PAGE_MS` limit."""
    page = browser.new_page(viewport={"width": size[0], "height": size[1]})
    page.set_default_timeout(T_PAGE_MS)
    page.goto(app.url)
    page.locator(ready).wait_for()
    return page


def open_page_in_control(browser, app, size, pin: str):
    """A tab of ``size`` on the app that is in control: it takes control with ``pin`` when no
    station holds it (the screenshot scripts, where a previous tab may already hold it)."""
    page = open_page(browser, app, size)
    if app.session.snapshot().control.controller is None:
        _take_control(page, pin)
    page.wait_for_function("document.querySelector('#mt-control').dataset.mine === '1'")
    return page


def _sample_ct_ready(s) -> bool:
    snap = s.snapshot()
    return snap.job is not None and snap.job.done and snap.head_mesh is not None


@contextmanager
def served_locked_sample(tmp_path, monkeypatch, port, config: dict | None = None, camera_factory=None,
                         sample_plan: bool = False):
    """A started session (home ``tmp_path``, sim robot, PIN 2468, plus ``config``) with the sample
    CT loaded and all its fiducials confirmed and locked (the local operator did it), and with
    ``sample_plan`` the sample path; served by the web app on ``port``. Yields ``(session, app)``."""
    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp

    monkeypatch.setenv("MONOTRACKER_HOME", str(tmp_path))
    s = Session(SessionConfig(home=tmp_path, **{"robot": "sim", "arm_pin": "2468", **(config or {})}),
                camera_factory=camera_factory)
    s.start()
    try:
        assert s.load_sample_ct().ok
        _wait(lambda: _sample_ct_ready(s), what="sample CT")
        for f in s.snapshot().fiducials:
            assert s.set_fiducial_status(f.id, "confirmed").ok
        assert s.confirm_fiducials().ok
        if sample_plan:
            assert s.use_sample_plan().ok
        app = MonoTrackerApp(s, "127.0.0.1", port, **APP_OPTIONS)
        app.start()
        try:
            yield s, app
        finally:
            app.stop()
    finally:
        s.shutdown()
