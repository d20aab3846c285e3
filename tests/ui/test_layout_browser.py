"""The layout planner in a real browser (headless Chromium, 1280x800; issue 31): at the Plan step a
quick layout plan from the page's "Plan layout" button; the page shows what to expect (the
predicted error at the target, the engine's own figures), the numbered suggested balls in its
table, and the error map, the numbered balls and the planned camera are sent to the 3D view and
the suggested balls drawn on the step's slices (viser draws 3D labels in the canvas: those are
checked through the tab's scene state; tests/ui/test_layout_panel.py and test_layout_slices.py
check what is drawn).

Every wait is on state (the session's snapshot, the tab's scene keys, the page's elements), never
on a fixed sleep, so the test holds on a loaded machine.
"""

from __future__ import annotations

import numpy as np
import pytest

from browser_helpers import _click, _msg, _take_control, _wait, open_page, served_locked_sample

pytestmark = pytest.mark.timeout(900)


def _layout_done(s):
    lay = s.snapshot().layout
    return lay is not None and lay.job.done


def test_plan_step_plans_a_layout_and_shows_the_map_and_numbered_balls(tmp_path, monkeypatch, port, browser,
                                                                      artifacts):
    with served_locked_sample(tmp_path, monkeypatch, port, sample_plan=True) as (s, app):
        page = open_page(browser, app, (1280, 800))
        assert "in control" in _take_control(page, "2468")
        _click(page, "2 Plan")
        view = app.views()[0]
        _wait(lambda: view.step == "plan", what="the tab at the Plan step")
        page.locator("#mt-layout").first.wait_for(state="attached")
        _wait(lambda: view.steps["plan"].layout.h_quick.value is True, what="quick search ticked (the default)")
        _click(page, "Plan layout")
        _wait(lambda: _layout_done(s), what=lambda: f"the layout plan to end (last: {_msg(page)})")
        lay = s.snapshot().layout
        assert lay.job.error is None and lay.ready, lay.job
        n = len(lay.balls_lps_mm)
        assert n == 9  # the page's default count

        # what to expect, as the engine predicted it (mean / 95 % / trusted of the suggestion)
        table = page.locator("#mt-layout-table").first
        table.wait_for()
        a = lay.suggestion.all_seen
        row = page.locator("#mt-layout-table tr", has_text="suggestion, planned camera").first
        assert "predicted error at the target" in table.inner_text()
        assert row.inner_text().split()[-4:] == [f"{a.mean_mm:.2f}", f"{a.p95_mm:.2f}",
                                                  f"{100 * a.trusted:.0f}", "%"], row.inner_text()
        # the suggested positions, numbered 1..n with their LPS centres
        balls = page.locator("#mt-layout-balls").first.inner_text()
        p = np.asarray(lay.balls_lps_mm)[n - 1]
        assert f"{n}\t{p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}" in balls, balls
        assert "Map on the head" in page.locator("#mt-layout").first.inner_text()

        # the 3D view: the map, the numbered balls (S1..Sn) and the camera were sent for this layout
        # (viser draws the labels in the canvas, not as page text: the tab's scene key is the state)
        _wait(lambda: (view.scene_keys.get("layout") or (False,))[0]
              and view.scene_keys["layout"][1] is s.snapshot().layout.balls_lps_mm, what="the layout drawn in 3D")
        # the step's slices were drawn with the suggested balls (their cache key holds them)
        _wait(lambda: (view.scene_keys.get(("slices", "plan")) or (None,))[-1] is not None,
              what="the Plan step's slices with the suggested balls")
        page.screenshot(path=str(artifacts / "layout_plan_1280x800.png"))
        assert "Traceback" not in page.content()
        page.close()
