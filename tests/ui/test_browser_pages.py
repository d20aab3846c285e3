"""The browser tests' own pages (tests/ui/conftest.py): animation frames capped at
``BROWSER_FPS`` and WebGL contexts without multisampling, both set by init scripts. The same
browser's pages without the scripts are the peer: they show that the page asked for what the
scripts take away, so a script that stopped working fails here, not as a slower suite."""

from __future__ import annotations

import pytest
from browser_helpers import BROWSER_FPS

pytestmark = pytest.mark.timeout(300)

#: a page with one canvas (a data URL: no server; init scripts run on it as on the app's pages)
PAGE = "data:text/html,<canvas id=c width=64 height=64></canvas>"

#: the attributes a WebGL 2 context asked for multisampling gets, or null without WebGL
ATTRIBUTES_JS = """() => {
  const gl = document.getElementById('c').getContext('webgl2', {antialias: true});
  return gl ? gl.getContextAttributes() : null;
}"""

#: how many animation frames the page draws in ``ms`` of its own clock
FRAMES_JS = """ms => new Promise(done => {
  let n = 0;
  const t0 = performance.now();
  const tick = () => { n++; if (performance.now() - t0 < ms) requestAnimationFrame(tick); else done(n); };
  requestAnimationFrame(tick);
})"""


def _page(browser):
    page = browser.new_page()
    page.goto(PAGE)
    return page


def test_webgl_on_test_pages_has_no_multisampling(browser):
    plain = _page(browser.plain)
    asked = plain.evaluate(ATTRIBUTES_JS)
    assert asked is not None, "no WebGL 2 in this chromium: the 3D view's tests cannot run"
    assert asked["antialias"] is True  # what a page asking for it gets without the script
    got = _page(browser).evaluate(ATTRIBUTES_JS)
    assert got is not None and got["antialias"] is False


def test_test_pages_draw_at_most_browser_fps(browser):
    ms = 1000
    plain = _page(browser.plain).evaluate(FRAMES_JS, ms)
    capped = _page(browser).evaluate(FRAMES_JS, ms)
    # each bound holds on a loaded machine: a capped frame never comes early, and an idle page
    # without the cap draws at the display's rate (60 Hz here) unless starved to a third of it
    assert 1 <= capped <= BROWSER_FPS * ms / 1000 + 2
    assert plain > 3 * BROWSER_FPS * ms / 1000
