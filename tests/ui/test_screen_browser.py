"""The surgeon's screen in a real browser (headless Chromium; issue 33): at 1280x800, 1920x1080
and 2560x1440 the live overlay fills the main view in Register and Robot (measured on screen against
the space the docked panels leave), no status text overflows its box, and with every fiducial
hidden no tip or angle error is shown as a live number. One served app for all of it; every wait
is on state. Screenshots of each step go to test-artifacts/ui/screen_<step>_<size>.jpg."""

from __future__ import annotations

import pytest

from browser_helpers import _click, _wait, open_page, served_locked_sample

pytestmark = pytest.mark.timeout(1200)

SIZES = ((1280, 800), (1920, 1080), (2560, 1440))

#: the live image in the main view and the docked panels beside it, CSS px
MEASURE_JS = """() => {
  const img = document.querySelector('div:has(> #mt-live-main) + div img');
  const reg = e => { const el = document.querySelector(`[data-dock-region="${e}"]`);
                     return el ? el.getBoundingClientRect().width : 0; };
  if (!img) return null;
  const r = img.getBoundingClientRect();
  return {x: r.left, y: r.top, w: r.width, h: r.height, natural: img.naturalWidth,
          left: reg('left'), right: reg('right'), vw: innerWidth, vh: innerHeight};
}"""

#: every status / step text that is shown: its text must not overflow its own box nor its panel
OVERFLOW_JS = """() => {
  const bad = [];
  const sel = '.mt-row, .mt-alarm, .mt-since, .mt-msg, .mt-state b, .mt-state span, .mt-control, .mt-alert, '
            + '.mt-banner-ok, .mt-banner-bad';
  for (const el of document.querySelectorAll(sel)) {
    const r = el.getBoundingClientRect();
    if (r.width === 0 || r.height === 0) continue;  // not shown (another step, a hidden folder)
    const box = el.closest('[data-dock-region], [data-floating-window]');
    const p = box ? box.getBoundingClientRect() : {left: 0, right: innerWidth};
    const what = `${el.className}: ${el.textContent.slice(0, 60)}`;
    if (el.scrollWidth > el.clientWidth + 1) bad.push(`overflows its box: ${what}`);
    if (r.right > p.right + 1 || r.left < p.left - 1) bad.push(`outside its panel: ${what}`);
  }
  for (const el of document.querySelectorAll('.mt-state')) {
    if (el.getBoundingClientRect().height > 0 && el.scrollHeight > el.clientHeight + 1)
      bad.push(`state block cut: ${el.textContent}`);
  }
  const alarms = [...document.querySelectorAll('.mt-alarm')].map(a => a.getBoundingClientRect())
                 .filter(r => r.height > 0);
  for (let i = 1; i < alarms.length; i++)
    if (alarms[i].top < alarms[i - 1].bottom - 1) bad.push('alarms overlap');
  return bad;
}"""


#: the live image fills the main view: as wide as the space the docked panels leave, or as the
#: window's height (less 100 px of header and caption) allows with its aspect kept, within 5 %
FILLS_JS = """() => {
  const m = (%s)();
  if (!m || m.natural < 300 || m.w === 0) return false;
  const allowed = Math.min(m.vw - m.left - m.right, (m.vh - 100) * m.w / m.h);
  return m.w >= 0.95 * allowed;
}""" % MEASURE_JS


def _live_image(page):
    """The live image's geometry once a real frame (not the 96 px placeholder) is shown and the
    page has laid it out to fill the main view (waited on: the docked panels' widths and the
    stylesheet arrive in separate messages); a clear failure with the geometry otherwise."""
    try:
        page.wait_for_function(FILLS_JS, timeout=60_000)
    except Exception:  # noqa: BLE001 - the assertion below says what the page shows
        pass
    return page.evaluate(MEASURE_JS)


def _overflow(page):
    """What overflows once the page has settled: a step switch re-lays the dock panels out over a
    few animation frames (a panel's rows were seen outside it once, in CI, right after '1 CT'),
    so the check waits (on the page's state, up to 15 s) for nothing to overflow and then returns
    what still does - a layout that stays wrong still fails, with its texts."""
    try:
        page.wait_for_function(f"(() => ({OVERFLOW_JS})().length === 0)()", timeout=15_000)
    except Exception:  # noqa: BLE001 - the caller's assertion says what overflows
        pass
    return page.evaluate(OVERFLOW_JS)


def _shoot(page, artifacts, step, w, h):
    page.screenshot(path=str(artifacts / f"screen_{step}_{w}x{h}.jpg"), type="jpeg", quality=60)


def test_overlay_fills_the_main_view_texts_fit_and_no_stale_number(tmp_path, monkeypatch, port, browser, artifacts):
    sizes = {}
    # the camera at 15 fps, not 30: the test checks where the live image lies and that its texts
    # fit, not the pose rate; the twin camera's render process and pose thread took ~33 of the
    # test's ~100 CPU s at 30 fps (55.6 -> 45.9 s, issue 35; 15 fps stays above the 0.1 s
    # freeze gate, as in test_calibration_step.py)
    with served_locked_sample(tmp_path, monkeypatch, port, {"camera_fps": 15.0}, sample_plan=True) as (s, app):
        assert s.start_camera().ok
        _wait(lambda: s.snapshot().pose is not None and s.snapshot().pose.trusted, what="a trusted pose")
        for w, h in SIZES:
            page = open_page(browser, app, (w, h))
            for step, label in (("register", "3 Register"), ("robot", "4 Robot")):
                _click(page, label)
                m = _live_image(page)
                # the space the docked panels leave (measured in the page, not our own constants)
                free_w = m["vw"] - m["left"] - m["right"]
                # as large as the window allows with the aspect kept: the free width, or the
                # window's height (less the panel's header and caption) times the aspect
                allowed = min(free_w, (m["vh"] - 100) * m["w"] / m["h"])
                assert m["w"] >= 0.95 * allowed, (step, w, h, allowed, m)
                assert m["x"] >= m["left"] - 1 and m["x"] + m["w"] <= m["vw"] - m["right"] + 1, (step, m)
                assert m["y"] + m["h"] <= m["vh"] + 1, (step, m)
                sizes[(step, w, h)] = (round(m["w"]), round(m["h"]))
                bad = _overflow(page)
                assert not bad, (step, w, h, bad)
                _shoot(page, artifacts, step, w, h)
            for step, label in (("ct", "1 CT"), ("plan", "2 Plan")):
                _click(page, label)
                page.wait_for_function("(() => { const i = document.querySelector("
                                       "'div:has(> #mt-live-main) + div img'); "
                                       "return !i || i.getBoundingClientRect().width === 0; })()")
                bad = _overflow(page)
                assert not bad, (step, w, h, bad)
                _shoot(page, artifacts, step, w, h)
            page.close()
        print("live overlay on screen (CSS px):", sizes)
        # every fiducial hidden: the Robot panel shows no tip / angle error as a live number
        page = open_page(browser, app, SIZES[0])
        _click(page, "4 Robot")
        page.locator("#mt-fig-tip").wait_for()
        assert s.inject_fault("occlude-all").ok
        _wait(lambda: s.snapshot().pose is not None and not s.snapshot().pose.trusted, what="pose not trusted")
        page.wait_for_function("document.querySelector('#mt-fig-tip').dataset.live === '0' && "
                               "document.querySelector('#mt-fig-angle').dataset.live === '0'")
        for key in ("tip", "angle"):
            text = page.locator(f"#mt-fig-{key}").inner_text()
            assert "mm" not in text.split("stale")[0] and "°" not in text, text
            assert "stale since" in text or "not available" in text, text
        bad = _overflow(page)  # with the occlusion alarms up
        assert not bad, bad
        _shoot(page, artifacts, "robot_occluded", *SIZES[0])
        page.close()


#: the docked panels' regions as the page lays them out, CSS px
DOCKS_JS = """() => { const reg = e => { const el = document.querySelector(`[data-dock-region="${e}"]`);
  return el ? el.getBoundingClientRect().width : 0; };
  return {left: reg('left'), right: reg('right'), vw: innerWidth, dpr: devicePixelRatio}; }"""


def _wait_for_panels(view, page, px: dict, what: str) -> None:
    """Until the server has settled on the panels ``px`` for this page: the canvas it reported
    came back after the panel widths now set, and those widths are ``px``'s."""
    _wait(lambda: view._canvas is not None and view._panel_width == (px["status"], px["steps_main_live"]),
          what=lambda: f"{what} (server: wide={view._wide}, panels {view._panel_width}, page "
                       f"{page.evaluate(DOCKS_JS)}, canvas reported {view.client.camera.image_width} px)")


def test_layout_switch_reads_the_pages_css_width_on_a_hidpi_screen(tmp_path, monkeypatch, port, browser):
    """On a screen with devicePixelRatio 2, a 1440x900 page (narrower than the wide layout's
    threshold, ``status.WIDE_PX``) keeps the compact panels and the live image is encoded for
    the width it is shown at; resized to 1920x1080 it switches to the wide ones. viser's camera
    message gives the canvas in drawing-buffer px (2x here): the switch read it as the page's
    width and picked the wide panels on the 1440 px page (ui/page_width.py)."""
    from monotracker.ui.status import PANEL_PX, PANEL_PX_WIDE, WIDE_PX

    from browser_helpers import T_PAGE_MS

    with served_locked_sample(tmp_path, monkeypatch, port, sample_plan=True) as (s, app):
        page = browser.new_page(viewport={"width": 1440, "height": 900}, device_scale_factor=2)
        page.set_default_timeout(T_PAGE_MS)
        page.goto(app.url)
        page.locator("#mt-control").wait_for()
        view = app.views()[0]
        _click(page, "3 Register")
        _wait(lambda: view.step == "register", what="the tab at Register")
        for (w, h), wide in (((1440, 900), False), ((1920, 1080), True)):
            if w != 1440:
                page.set_viewport_size({"width": w, "height": h})
            assert (w >= WIDE_PX[1]) == wide  # the truth: the page's CSS width against the threshold
            px = PANEL_PX_WIDE if wide else PANEL_PX
            _wait_for_panels(view, page, px, f"the {'wide' if wide else 'compact'} panels at {w}x{h}")
            page.wait_for_function(f"(() => {{ const d = ({DOCKS_JS})(); return d.vw === {w} && "
                                   f"Math.abs(d.left - {px['status']}) <= 6 && "
                                   f"Math.abs(d.right - {px['steps_main_live']}) <= 6; }})()")
            d = page.evaluate(DOCKS_JS)
            assert d["dpr"] == 2, d
            # the stream is encoded for the width the image is shown at, never wider than the
            # space the docked panels leave (CSS px, measured in the page)
            assert view.live_width <= d["vw"] - d["left"] - d["right"], (view.live_width, d)
        page.close()
