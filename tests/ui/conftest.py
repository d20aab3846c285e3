"""Browser fixtures: Debian's chromium driven by Playwright (never `playwright install`)."""

from __future__ import annotations

import atexit
import os
import shlex
import shutil
import socket
import tempfile
from pathlib import Path

import pytest

# BROWSER_FPS (the most animation frames a second a test page draws) lives in browser_helpers:
# a test module imports it from there, never ``from conftest import``, which takes whichever
# folder's conftest pytest loaded last when several test folders run in one call
from browser_helpers import BROWSER_FPS

CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run"]
ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts" / "ui"


def chromium_path() -> str:
    for c in (os.environ.get("MONOTRACKER_CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium")):
        if c and Path(c).exists():
            return c
    raise RuntimeError("chromium not found: scripts/test.sh installs Debian's chromium (apt-get install -y chromium)")


#: niceness of the browser in the tests (the launcher's process and its session's autogroup):
#: normal, as the CPU hogs beside the tests are. In the OR the page is shown on another device (a
#: workstation or a tablet), so the load on the tracker's cores never slows the page; here the
#: browser shares them. It ran at nice 10 (issue 35, before its pages' frame cap): Playwright
#: starts the browser in a session of its own, so the kernel's autogroup scheduling gave its
#: whole session the weight of one nice-10 task (110 against 1024): with 4 hogs beside the tests
#: it got 0.1-0.2 of the 2 cores, and opening a page of the sample scene costs chromium ~15-20
#: CPU s (SwiftShader in its GPU process), so a first click waited for minutes (issue 33: 4 of the
#: first 5 browser tests failed on Playwright's 120 s limits). At nice 0 the browser's session
#: gets at most an equal share (one core of two) when the tests' session is busy too, and takes
#: little once a page is drawn (its frames are capped at :data:`BROWSER_FPS`). Run as root (CI)
#: chromium raised its own threads' priority (nice -8 was seen): the launcher drops that right.
BROWSER_NICE = 0


def _own_session() -> str:
    """Put the test process (the app under test: its pose pipeline, its camera and control
    processes, which inherit it) in a session of its own, as a deployed service runs (systemd
    starts each service in its own session). The kernel shares the CPU between sessions first
    (autogroups), then between a session's threads: CPU hogs started beside the tests in the same
    session as them (``hogrun``, a CI step) otherwise compete with the app thread by thread, and
    with the browser in a session of its own taking half the 2 cores, the pose pipeline got 0.09
    of a core and every pose came in stale (issue 33: 8 poses/s, 60 % over the 150 ms limit;
    with the app in its own session beside the same 4 hogs, 19.7 poses/s). Not done when the
    tests' standard input is a terminal (Ctrl-C there must still reach them) or
    ``MONOTRACKER_TEST_OWN_SESSION=0``; a process-group leader (pytest started straight from an
    interactive shell) cannot, and keeps its session. Returns what was done, for the log."""
    if os.environ.get("MONOTRACKER_TEST_OWN_SESSION", "1") == "0":
        return "kept (MONOTRACKER_TEST_OWN_SESSION=0)"
    try:
        if os.isatty(0):
            return "kept (standard input is a terminal)"
    except OSError:
        pass
    try:
        os.setsid()
        return "own session"
    except OSError as e:
        return f"kept ({e.strerror})"


#: done when pytest first imports this file (collection, before any app starts)
OWN_SESSION = _own_session()


def display_browser_path() -> str:
    """A launcher for :func:`chromium_path` at niceness :data:`BROWSER_NICE` (the process and its
    session's autogroup) that cannot raise its priority again (``setpriv`` drops CAP_SYS_NICE where
    util-linux has it; the browser's child processes inherit both). A small shell script in a
    temporary folder."""
    folder = Path(tempfile.mkdtemp(prefix="mt-browser-"))
    atexit.register(shutil.rmtree, folder, True)
    script = folder / "chromium-nice"
    browser = shlex.quote(chromium_path())
    script.write_text("#!/bin/sh\n"
                      f"echo {BROWSER_NICE} > /proc/self/autogroup 2>/dev/null\n"
                      "if command -v setpriv >/dev/null 2>&1; then\n"
                      f"  exec setpriv --bounding-set -sys_nice --inh-caps -sys_nice nice -n {BROWSER_NICE} {browser} \"$@\"\n"
                      "fi\n"
                      f"exec nice -n {BROWSER_NICE} {browser} \"$@\"\n")
    script.chmod(0o755)
    return str(script)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def port() -> int:
    return free_port()



#: the init script that caps ``requestAnimationFrame`` at :data:`BROWSER_FPS`: a callback asked
#: for runs at the animation frame after the next 1/BROWSER_FPS s boundary (all callbacks asked
#: within one period share a frame, as without the cap); ``cancelAnimationFrame`` cancels either stage.
#: The boundary is the next one strictly after the request (a frame drawn exactly on a boundary,
#: as the coarse clock often reads it, asked for the next one at once), and a frame that comes
#: before it (a timer may fire a fraction of a millisecond early) waits for the next frame after
#: it: frames at 15599.9 and 15607.3 ms were seen, two in one period, up to 9 frames in 1 s under
#: 4 CPU hogs, which failed test_browser_pages.test_test_pages_draw_at_most_browser_fps (bound 7).
FRAME_CAP_JS = """(() => {
  const period = 1000 / %s;
  const raf = window.requestAnimationFrame.bind(window);
  const caf = window.cancelAnimationFrame.bind(window);
  const pending = new Map();
  let next = 1;
  window.requestAnimationFrame = (cb) => {
    const id = next++;
    const target = (Math.floor(performance.now() / period) + 1) * period;   // strictly after now
    const later = () => pending.set(id, {timer: setTimeout(() => pending.set(id, {frame: raf(run)}),
                                                           Math.max(0, target - performance.now()))});
    const run = (ts) => {
      if (performance.now() < target) { later(); return; }
      pending.delete(id);
      cb(ts);
    };
    later();
    return id;
  };
  window.cancelAnimationFrame = (id) => {
    const p = pending.get(id);
    if (p === undefined) return;
    pending.delete(id);
    if (p.timer !== undefined) clearTimeout(p.timer);
    if (p.frame !== undefined) caf(p.frame);
  };
})();""" % BROWSER_FPS

#: the init script that gives every WebGL context of a test page no multisample anti-aliasing
#: (``antialias: false`` whatever the page asks; viser's client asks for react-three-fiber's
#: default, 4x MSAA). Without a GPU, chromium's SwiftShader renders and resolves the samples in
#: software at every frame: in the end-to-end test its GPU process took 27 CPU s of a 46 s run
#: with them and 7-10 s of a 24-30 s run without (alternating pairs, quiet, 2026-11-30); the
#: calibration, screen, two-tab, layout and navigation browser tests 166 -> 112 s together. The
#: tests check the page's widgets, the session, where a click lands and the pixels inside images
#: (slices, the camera view), never how smooth a 3D edge looks. Only the tests' pages: the app
#: serves viser's client unchanged.
NO_MSAA_JS = """(() => {
  const getContext = HTMLCanvasElement.prototype.getContext;
  HTMLCanvasElement.prototype.getContext = function (type, attrs) {
    if (type === "webgl2" || type === "webgl" || type === "experimental-webgl") {
      attrs = Object.assign({}, attrs || {}, {antialias: false});
    }
    return getContext.call(this, type, attrs);
  };
})();"""


class CappedBrowser:
    """A Playwright ``Browser`` whose new pages and contexts draw at most :data:`BROWSER_FPS`
    frames a second, without multisampling (:data:`FRAME_CAP_JS` and :data:`NO_MSAA_JS` added
    before any page script runs); everything else is the browser's own (attributes are passed
    through)."""

    def __init__(self, browser):
        self._browser = browser

    def new_context(self, **kw):
        ctx = self._browser.new_context(**kw)
        ctx.add_init_script(FRAME_CAP_JS)
        ctx.add_init_script(NO_MSAA_JS)
        return ctx

    @property
    def plain(self):
        """The browser itself: its pages get neither init script (the peer in their tests)."""
        return self._browser

    def new_page(self, **kw):
        ctx = self.new_context(**kw)
        page = ctx.new_page()
        return page

    def __getattr__(self, name):
        return getattr(self._browser, name)


@pytest.fixture(scope="session")
def browser():
    """One headless chromium for the whole run (issue 35: it was launched again for every test
    module), its pages capped at :data:`BROWSER_FPS` and drawn without multisampling
    (:class:`CappedBrowser`). Each test opens
    its own pages; :func:`_close_pages_left_open` closes whatever a test left open, so no tab of
    an earlier test keeps rendering (or reconnecting to a stopped server) beside the next one."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=display_browser_path(), headless=True, args=CHROMIUM_ARGS)
        yield CappedBrowser(b)
        b.close()


@pytest.fixture(autouse=True)
def _close_pages_left_open(request):
    """After a test that used :func:`browser`: close its pages and contexts (a page left open
    kept rendering the 3D view in software until its module ended, taking CPU from the tests
    after it)."""
    yield
    if "browser" not in request.fixturenames:
        return
    b = request.getfixturevalue("browser")
    for ctx in list(b.contexts):
        try:
            ctx.close()
        except Exception:  # noqa: BLE001 - a context the test already closed, or a browser gone: nothing left to close
            pass


@pytest.fixture
def artifacts() -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS
