"""When the server goes away the page says so: "CONNECTION LOST - robot state unknown" over a
greyed state block (viser's client marks its GUI with pointer-events:none while disconnected;
the stylesheet shows the banner then)."""

from __future__ import annotations

import pytest
from browser_helpers import APP_OPTIONS, open_page

pytestmark = pytest.mark.timeout(600)


def test_connection_lost_banner(tmp_path, port, browser):
    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp

    s = Session(SessionConfig(home=tmp_path, arm_pin="2468"))
    app = MonoTrackerApp(s, "127.0.0.1", port, **APP_OPTIONS)
    app.start()
    try:
        page = open_page(browser, app, (1280, 800), ready="#mt-robot-state")
        assert not page.locator("#mt-conn-lost").is_visible()  # connected: no banner
        app.stop()
        page.locator("#mt-conn-lost").wait_for(state="visible")
        assert "CONNECTION LOST" in page.locator("#mt-conn-lost").inner_text()
        assert "robot state unknown" in page.locator("#mt-conn-lost").inner_text()
        page.close()
    finally:
        app.stop()
        s.shutdown()
