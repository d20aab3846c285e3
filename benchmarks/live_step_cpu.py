"""Where the cores go while a browser test's tab watches the live Register step: per-thread CPU
of the app, its camera and control processes and the browser's processes, and what the pose
pipeline delivers (camera fps, pose age at arrival, the stages' times) in the same window.

    python benchmarks/live_step_cpu.py [--seconds 20] [--hogs 4] [--size 1600x1000] [--no-page]

Set up as the browser tests are (``tests/ui``: the sample CT and plan locked, the app with the
tests' ``APP_OPTIONS``, one headless chromium tab at normal priority with its frames capped as in
``tests/ui/conftest.py``, in control, on Register), then the camera is started from the page and
after a short settle ``--seconds`` are measured. ``--no-page``: no tab open (the app alone).
Run through ``/work/bin/cpu --quiet`` for figures; ``--hogs`` busy loops at nice 0 beside it
(``_hogs.py``; in this process's session and autogroup, as ``MONOTRACKER_TEST_HOGS`` and
``hogrun`` put them).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "app"))
sys.path.insert(0, str(ROOT / "tests" / "ui"))

import proc_cpu  # noqa: E402
from _hogs import hogs  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--hogs", type=int, default=0)
    ap.add_argument("--size", default="1600x1000")
    ap.add_argument("--no-page", action="store_true")
    ap.add_argument("--settle", type=float, default=5.0)
    ap.add_argument("--step", default="3 Register", help="the step the tab shows (its button's label)")
    ap.add_argument("--no-live", action="store_true", help="untick 'Live image in the main view' (no stream to the tab)")
    ap.add_argument("--browser-nice", type=int, default=None,
                    help="the browser's niceness (its session's autogroup too; default: tests/ui/conftest.py's BROWSER_NICE)")
    ap.add_argument("--dump", default="", help="write every pose's arrival, age and stages (JSON lines) here")
    a = ap.parse_args()
    w, h = (int(v) for v in a.size.split("x"))

    from browser_helpers import APP_OPTIONS, _click, _take_control, _wait, open_page
    import conftest
    from conftest import CHROMIUM_ARGS, CappedBrowser, display_browser_path, free_port

    if a.browser_nice is not None:
        conftest.BROWSER_NICE = a.browser_nice
    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp
    from playwright.sync_api import sync_playwright

    home = Path(tempfile.mkdtemp(prefix="mt-livecpu-"))
    os.environ["MONOTRACKER_HOME"] = str(home)
    s = Session(SessionConfig(home=home, camera="sim", trajectory="breathing", robot="sim", arm_pin="2468"))
    arrivals: list = []
    orig = s._loop.on_pose

    def on_pose(sample, now):
        st = dict(getattr(sample, "stages", None) or {})
        st.update(code=str(getattr(sample, "code", "")), ok=bool(sample.ok), n=int(sample.n_matched or 0),
                  frame=int(getattr(sample, "frame_index", -1) or -1))
        arrivals.append((now, now - sample.t_capture, st))
        orig(sample, now)

    s._loop.on_pose = on_pose
    s.start()
    assert s.load_sample_ct().ok
    _wait(lambda: s.snapshot().job is not None and s.snapshot().job.done and s.snapshot().head_mesh is not None)
    for f in s.snapshot().fiducials:
        assert s.set_fiducial_status(f.id, "confirmed").ok
    assert s.confirm_fiducials().ok
    assert s.use_sample_plan().ok
    app = MonoTrackerApp(s, "127.0.0.1", free_port(), **APP_OPTIONS)
    app.start()
    with hogs(a.hogs, own_session=False), sync_playwright() as p:
        b = CappedBrowser(p.chromium.launch(executable_path=display_browser_path(), headless=True,
                                            args=CHROMIUM_ARGS))
        if not a.no_page:
            page = open_page(b, app, (w, h))
            _take_control(page, "2468")
            _click(page, "3 Register")
            _click(page, "Start camera")
            if a.no_live:
                page.get_by_label("Live image in the main view").uncheck()
                _wait(lambda: not app.views()[0].h_live_main.value, what="live image unticked")
            if a.step != "3 Register":
                _click(page, a.step)
        else:
            assert s.start_camera().ok
        _wait(lambda: s.snapshot().camera.running, what="camera running")
        time.sleep(a.settle)
        n0 = len(arrivals)
        t0, c0 = time.monotonic(), proc_cpu.snapshot()
        trusted = 0
        samples = 0
        reasons: dict = {}
        while time.monotonic() - t0 < a.seconds:
            time.sleep(0.1)
            samples += 1
            snap = s.snapshot()
            trusted += bool(snap.pose is not None and snap.pose.trusted)
            if snap.pose is not None and not snap.pose.trusted:
                why = (snap.pose.reason or snap.pose.code or "?").split(":")[0]
                reasons[why] = reasons.get(why, 0) + 1
        wall = time.monotonic() - t0
        c1 = proc_cpu.snapshot()
        by_class, by_thread = proc_cpu.cpu_use(c0, c1, wall)
        camproc = getattr(s._loop.camera.rig, "_camproc", None)
        cam_pid = getattr(camproc, "pid", None)
        per_pid = {f"{k[0]} {'(camera) ' if k[1] == cam_pid else ''}{k[1]}": (v - c0.get(k, 0.0)) / wall
                   for k, v in c1.items() if k[0] != "server python"}
        rows = arrivals[n0:]
        load = os.getloadavg()[0]
        b.close()
    app.stop()
    s.shutdown()

    if a.dump:
        import json

        with open(a.dump, "w") as f:
            for r in arrivals:
                f.write(json.dumps({"t": r[0], "age": r[1], **{k: v for k, v in r[2].items()
                                                               if isinstance(v, (int, float, str, bool))}}) + "\n")
    print(f"{a.size} page={'no' if a.no_page else a.step + (' no live' if a.no_live else '')} browser nice {conftest.BROWSER_NICE} hogs={a.hogs} {wall:.1f} s, load {load:.1f}")
    if rows:
        age = 1000 * np.array([r[1] for r in rows])
        gaps = 1000 * np.diff([r[0] for r in rows]) if len(rows) > 1 else np.zeros(1)
        print(f"poses {len(rows) / wall:.1f}/s; age at arrival p50/p95 {np.percentile(age, 50):.0f}/"
              f"{np.percentile(age, 95):.0f} ms ({100 * np.mean(age > 150):.0f} % over 150 ms); gap p50/p95/max "
              f"{np.percentile(gaps, 50):.0f}/{np.percentile(gaps, 95):.0f}/{gaps.max():.0f} ms; "
              f"snap.pose.trusted {100 * trusted / max(samples, 1):.0f} % of 0.1 s samples")
        if reasons:
            print("  not trusted: " + ", ".join(f"{k} {100 * v / max(samples, 1):.0f} %"
                                               for k, v in sorted(reasons.items(), key=lambda kv: -kv[1])))
        for k in ("render_s", "arrived_s", "estimate_s", "estimate_cpu_s", "detect_s", "register_s"):
            v = 1000 * np.array([r[2].get(k, np.nan) for r in rows], float)
            if np.isfinite(v).any():
                print(f"  {k:15s} p50 {np.nanpercentile(v, 50):6.1f} ms  p95 {np.nanpercentile(v, 95):6.1f} ms")
    else:
        print("no pose arrived")
    print("cores by process:", ", ".join(f"{k} {v:.2f}" for k, v in sorted(by_class.items(), key=lambda x: -x[1])
                                        if v >= 0.005))
    print("processes:", ", ".join(f"{k} {v:.2f}" for k, v in sorted(per_pid.items(), key=lambda x: -x[1])
                                  if v >= 0.005))
    print("app threads:", ", ".join(f"{k} {v:.2f}" for k, v in sorted(by_thread.items(), key=lambda x: -x[1])
                                    if v >= 0.005))


if __name__ == "__main__":
    main()
