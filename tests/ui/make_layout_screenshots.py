"""Screenshots of the Plan step with a planned ball and camera layout (issue 31) at 1280x800 and
1920x1080 -> docs/img/ui_layout_<size>.jpg. The layout is planned from the page ("Plan layout",
quick search, 9 balls); the 3D view is then turned to show the head with its error map, the
numbered suggested balls and the planned camera side by side.

    .venv/bin/python tests/ui/make_layout_screenshots.py   (from the repository root; needs chromium)
"""
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, "tests/ui")
from browser_helpers import _click, _wait, open_page_in_control
from conftest import CHROMIUM_ARGS, display_browser_path, free_port
from make_screenshots import _close_notifications
from playwright.sync_api import sync_playwright

from monotracker.engine import Session, SessionConfig
from monotracker.ui.app import MonoTrackerApp

out = Path("docs/img")
out.mkdir(parents=True, exist_ok=True)
home = Path(tempfile.mkdtemp(prefix="layout-shots"))
s = Session(SessionConfig(home=home, camera="sim-points", robot="sim", arm_pin="2468", control_process=False))
s.start()
s.load_sample_ct()
_wait(lambda: s.snapshot().job is not None and s.snapshot().job.done and s.snapshot().head_mesh is not None,
      timeout=600, what="ct")
for f in s.snapshot().fiducials:
    s.set_fiducial_status(f.id, "confirmed")
assert s.confirm_fiducials().ok and s.use_sample_plan().ok
app = MonoTrackerApp(s, "127.0.0.1", free_port())
app.start()


def side_view(lay, mesh):
    """Every tab's 3D camera beside the head and the planned camera (scene metres)."""
    c = (np.asarray(mesh.vertices).min(axis=0) + np.asarray(mesh.vertices).max(axis=0)) / 2
    e = np.asarray(lay.T_ct_cam)[:3, 3]
    d = (e - c) / np.linalg.norm(e - c)
    side = np.cross(d, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    look = c + 0.5 * (e - c)
    pos = look + 800.0 * side + 150.0 * np.array([0.0, 0.0, 1.0])
    for client in app.server.get_clients().values():
        with client.atomic():
            client.camera.up_direction = (0.0, 0.0, 1.0)
            client.camera.position = tuple(pos * 1e-3)
            client.camera.look_at = tuple(look * 1e-3)


try:
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=display_browser_path(), headless=True, args=CHROMIUM_ARGS)
        for w, h in ((1280, 800), (1920, 1080)):
            page = open_page_in_control(b, app, (w, h), "2468")
            _click(page, "2 Plan")
            if s.snapshot().layout is None:
                _click(page, "Plan layout")
                _wait(lambda: s.snapshot().layout is not None and s.snapshot().layout.job.done, timeout=900,
                      what="layout")
                print("layout:", s.snapshot().layout.job, flush=True)
            page.locator("#mt-layout-table").first.wait_for()
            time.sleep(2)
            side_view(s.snapshot().layout, s.snapshot().head_mesh)
            page.locator("#mt-layout-table").first.scroll_into_view_if_needed()
            time.sleep(4)
            _close_notifications(page)
            page.screenshot(path=str(out / f"ui_layout_{w}x{h}.jpg"), type="jpeg", quality=70)
            print("shot", w, h, flush=True)
            page.close()
finally:
    app.stop()
    s.shutdown()
