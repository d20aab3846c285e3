"""``MonoTrackerApp(environment_map=...)``: what a newly connecting page is sent (viser's
broadcast buffer, the scene state every new tab receives), without a browser."""

from __future__ import annotations

import pytest


def _environment_maps(app) -> list:
    """The environment-map messages a new tab would receive, oldest first."""
    from viser import _messages

    buf = app.server._websock_server._broadcast_buffer
    with buf.buffer_lock:
        msgs = [buf.message_from_id[k] for k in sorted(buf.message_from_id)]
    return [m for m in msgs if isinstance(m, _messages.EnvironmentMapMessage)]


@pytest.mark.parametrize("environment_map", [True, False])
def test_environment_map_option_reaches_the_page(tmp_path, port, environment_map):
    """False: every tab is told to draw without an HDR map (a message with ``hdri_data`` None:
    viser's client then uses the default lights only); True (the default): no such message, so
    the page keeps viser's own default map (its client draws the "city" HDR when no message
    says otherwise; viser/client/src/EnvironmentState.ts)."""
    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp

    s = Session(SessionConfig(home=tmp_path, arm_pin="2468"))
    app = MonoTrackerApp(s, "127.0.0.1", port, environment_map=environment_map)
    app.start()
    try:
        maps = _environment_maps(app)
        if environment_map:
            assert all(m.hdri_data is not None for m in maps), maps
        else:
            assert maps and maps[-1].hdri_data is None, maps
    finally:
        app.stop()
        s.shutdown()
