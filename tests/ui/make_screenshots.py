"""Screenshots of each web-app step at 1280x800, 1920x1080 and 2560x1440 -> docs/img/ui_<step>_<size>.jpg,
and of the navigation view (slices in the main view) in Plan and Robot (live needle tip) ->
docs/img/ui_navigation_<step>_<size>.jpg.

    .venv/bin/python tests/ui/make_screenshots.py [WxH ...]   (from the repository root; needs chromium;
                                                    default: all three sizes)
"""
import sys
import tempfile
import time
from pathlib import Path
sys.path.insert(0, "tests/ui")
from conftest import display_browser_path, CHROMIUM_ARGS, free_port
from browser_helpers import _click, _command, _wait, open_page_in_control
from monotracker.engine import Session, SessionConfig
from monotracker.ui.app import MonoTrackerApp
from playwright.sync_api import sync_playwright


def _close_notifications(page) -> None:
    """Close the browser's toasts (a headless browser draws WebGL in software, and viser says so in
    a toast over the top-left of the main view: not what an OR screen shows)."""
    page.evaluate("document.querySelectorAll('.mantine-Notification-root button').forEach(b => b.click())")
    time.sleep(0.5)


def main() -> None:
    """Make the screenshots (a function: the simulated camera's render process is spawned, and a
    spawned child imports this file again; at top level it would start a second app there)."""
    out = Path("docs/img"); out.mkdir(parents=True, exist_ok=True)
    home = Path(tempfile.mkdtemp(prefix="ui-shots"))
    # pictures, not a test: on a loaded machine the freshness gates are loosened so the pose stays trusted
    s = Session(SessionConfig(home=home, camera="sim", robot="sim", trajectory="breathing", arm_pin="2468",
                              camera_fps=15.0, max_pose_age_s=1.0, freeze_after_s=1.0,
                              control_process=False)); s.start()  # a control process may not start in time under load
    s.load_sample_ct()
    _wait(lambda: s.snapshot().job is not None and s.snapshot().job.done and s.snapshot().head_mesh is not None, what="ct")
    for f in s.snapshot().fiducials:
        s.set_fiducial_status(f.id, "confirmed")
    app = MonoTrackerApp(s, "127.0.0.1", free_port()); app.start()
    try:
        with sync_playwright() as p:
            b = p.chromium.launch(executable_path=display_browser_path(), headless=True, args=CHROMIUM_ARGS)
            sizes = [tuple(int(v) for v in a.split("x")) for a in sys.argv[1:]] or [(1280, 800), (1920, 1080), (2560, 1440)]
            for w, h in sizes:
                page = open_page_in_control(b, app, (w, h), "2468")
                for step, label in (("ct", "1 CT"), ("plan", "2 Plan"), ("register", "3 Register"), ("robot", "4 Robot")):
                    if step == "plan" and not s.snapshot().fiducials_locked:
                        s.confirm_fiducials(); s.use_sample_plan()
                    _click(page, label)
                    if step == "register" and not s.snapshot().camera.running:
                        _command(page, "Start camera")
                        _wait(lambda: s.snapshot().pose is not None and s.snapshot().pose.trusted, what="pose")
                    if step == "robot" and s.snapshot().robot.state == "disarmed":
                        # the local operator arms (the PIN pad flow is what tests/ui/test_e2e.py checks);
                        # on a loaded machine arming is refused while the pose is stale: try again
                        for _ in range(30):
                            _wait(lambda: s.snapshot().pose is not None and s.snapshot().pose.trusted, what="pose")
                            print("arm:", s.arm("2468"), flush=True)
                            if s.snapshot().robot.state == "armed":
                                break
                            time.sleep(1)
                        for _ in range(30):
                            if s.snapshot().robot.state in ("tracking", "holding"):
                                break
                            print("start:", s.start_tracking(), flush=True)
                            time.sleep(1)
                    if step in ("register", "robot"):  # the live image in the main view, laid out
                        page.wait_for_function("(() => { const i = document.querySelector("
                                               "'div:has(> #mt-live-main) + div img'); "
                                               "return i && i.naturalWidth >= 300 && i.getBoundingClientRect().width > 500; })()")
                    time.sleep(4)
                    _close_notifications(page)
                    page.screenshot(path=str(out / f"ui_{step}_{w}x{h}.jpg"), type="jpeg", quality=70)
                    print("shot", step, w, h, flush=True)
                    if step in ("plan", "robot"):  # the navigation view (slices) in the main view
                        page.locator("text=Slices in main view >> visible=true").first.click()
                        want = "tip" if step == "robot" else "target"
                        page.wait_for_function(f"document.querySelector('#mt-nav-{step}').dataset.source === '{want}'")
                        time.sleep(3)
                        _close_notifications(page)
                        page.screenshot(path=str(out / f"ui_navigation_{step}_{w}x{h}.jpg"), type="jpeg", quality=70)
                        print("shot navigation", step, w, h, page.locator(f"#mt-nav-{step}").inner_text(), flush=True)
                        page.locator("text=Slices in main view >> visible=true").first.click()
                page.close()
    finally:
        app.stop(); s.shutdown()


if __name__ == "__main__":
    main()
