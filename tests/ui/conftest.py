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

CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run"]
ARTIFACTS = Path(__file__).resolve().parents[2] / "test-artifacts" / "ui"


def chromium_path() -> str:
    for c in (os.environ.get("MONOTRACKER_CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium")):
        if c and Path(c).exists():
            return c
    raise RuntimeError("chromium not found: scripts/test.sh installs Debian's chromium (apt-get install -y chromium)")


#: niceness of the browser in the tests: in the OR the page is shown on another device (a
#: workstation or a tablet), not on the tracker's two cores. Headless chromium renders the 3D
#: view in software (SwiftShader) and, run as root (CI), raises its own threads' priority
#: (nice -8 was seen): it took the CPU from the pose pipeline, a contention no deployment has.
#: Playwright starts the browser in a session of its own, so the kernel's autogroup scheduling
#: shares the CPU between the browser's session and the app's as equals whatever each process's
#: nice: the launcher sets its session's autogroup nice too (/proc/self/autogroup).
BROWSER_NICE = 10


def display_browser_path() -> str:
    """A launcher for :func:`chromium_path` at niceness :data:`BROWSER_NICE` (the process and its
    session's autogroup) that cannot raise its priority again (``setpriv`` drops CAP_SYS_NICE where util-linux has it; the browser's
    child processes inherit both). A small shell script in a temporary folder."""
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


@pytest.fixture(scope="session")
def browser():
    """One headless chromium for the whole run (issue 35: it was launched again for every test
    module). Each test opens its own pages; :func:`_close_pages_left_open` closes whatever a
    test left open, so no tab of an earlier test keeps rendering (or reconnecting to a stopped
    server) beside the next one."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=display_browser_path(), headless=True, args=CHROMIUM_ARGS)
        yield b
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
