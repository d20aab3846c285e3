"""Overlay streaming to a real headless browser: frames per second and frame-to-screen latency.

    python benchmarks/web_overlay.py [--seconds 10] [--quick]

The web app (MonoTrackerApp, Register step) pushes 1280x720 frames through its own path
(draw_overlay + JPEG + viser GUI image) with a 20-bit frame number stamped in a corner. Debian's
chromium (Playwright, headless) reads the number back from the <img> on every animation frame
and notes Date.now(); latency = browser time seen - server time pushed (same machine clock).
Baseline in the same run: plain frames pushed to a GUI image without the overlay drawing.
Target (issue 9): >= 20 fps, < 100 ms.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

JS = """
() => { window.__seen = []; const c = document.createElement('canvas'); const ctx = c.getContext('2d', {willReadFrequently: true});
  let last = -1;
  function tick() {
    const imgs = [...document.querySelectorAll('img')].filter(i => i.naturalWidth === 1280);
    if (imgs.length) { const im = imgs[0]; c.width = 320; c.height = 16;
      ctx.drawImage(im, 0, 704, 320, 16, 0, 0, 320, 16);
      const d = ctx.getImageData(0, 0, 320, 16).data; let v = 0;
      for (let b = 0; b < 20; b++) { const x = b * 16 + 8, y = 8; const k = (y * 320 + x) * 4;
        v = (v << 1) | ((d[k] + d[k+1] + d[k+2]) / 3 > 127 ? 1 : 0); }
      if (v !== last) { last = v; window.__seen.push([v, Date.now()]); } }
    requestAnimationFrame(tick); }
  requestAnimationFrame(tick); }
"""


def camera_like_frame() -> np.ndarray:
    """A 1280x720 BGR frame with the content statistics of the simulated OR camera (smooth
    drape-blue background with sensor noise, a skin-coloured head with green balls): JPEG sizes
    like the real stream, unlike random noise (worst case) or a flat image (best case)."""
    import cv2

    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:720, 0:1280]
    img = np.dstack([120 + 40 * np.sin(x / 90.0), 90 + 30 * np.cos(y / 70.0), 50 + 0 * x]).astype(np.float32)
    cv2.ellipse(img, (700, 380), (230, 270), 10, 0, 360, (140, 160, 205), -1)
    for k in range(9):
        cv2.circle(img, (560 + 37 * k, 300 + 25 * ((k * 5) % 7)), 12, (60, 170, 60), -1)
    img += rng.normal(0, 3, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def run(seconds: float, overlay: bool) -> dict:
    from playwright.sync_api import sync_playwright

    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp
    from monotracker.ui.overlay import frame_code_strip

    home = Path(tempfile.mkdtemp())
    s = Session(SessionConfig(home=home))
    import socket

    with socket.socket() as so:
        so.bind(("127.0.0.1", 0))
        port = so.getsockname()[1]
    app = MonoTrackerApp(s, "127.0.0.1", port, stream_code=True)
    app.start()
    app._view_step = "register"
    app._auto_step = False
    app._show_step()
    base = camera_like_frame()
    stop = threading.Event()

    def pusher():
        i = 0
        while not stop.is_set():
            t0 = time.monotonic()
            img = np.roll(base, i * 7, axis=1)
            i += 1
            if overlay:
                app.push_frame(img, None, s.snapshot())
            else:
                import cv2

                app._push_count += 1
                strip = frame_code_strip(app._push_count)
                img = img.copy()
                img[-16:, :320] = strip
                app._pushed[app._push_count] = time.time()
                app.h_live.image = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
            stop.wait(max(0.0, 1 / 30 - (time.monotonic() - t0)))

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path="/usr/bin/chromium", headless=True,
                              args=["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                                    "--disable-component-update", "--disable-sync", "--no-first-run"])
        page = b.new_page(viewport={"width": 1600, "height": 1000})
        page.goto(app.url)
        page.wait_for_timeout(4000)
        th = threading.Thread(target=pusher, daemon=True)
        th.start()
        page.wait_for_timeout(1500)
        page.evaluate(JS)
        page.wait_for_timeout(int(seconds * 1000))
        seen = page.evaluate("window.__seen")
        stop.set()
        b.close()
    app.stop()
    s.shutdown()
    pushed = dict(app._pushed)
    lat = [t_seen - pushed[v] * 1000 for v, t_seen in seen if v in pushed]
    n = len(seen)
    span = (seen[-1][1] - seen[0][1]) / 1000 if n > 1 else float("nan")
    return {"fps": (n - 1) / span if n > 1 else 0.0, "lat_median": float(np.median(lat)) if lat else float("nan"),
            "lat_p95": float(np.percentile(lat, 95)) if lat else float("nan"), "frames": n, "pushed": len(pushed)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--quick", action="store_true", help="3 s per row")
    a = ap.parse_args()
    secs = 3.0 if a.quick else a.seconds
    rows = [("baseline: plain frame -> GUI image", run(secs, overlay=False)),
            ("web app: overlay + JPEG -> GUI image", run(secs, overlay=True))]
    import os

    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.overlay import draw_overlay

    img = camera_like_frame()
    with Session(SessionConfig(home=Path(tempfile.mkdtemp()))) as s:
        snap = s.snapshot()
        import cv2

        t0 = time.perf_counter()
        for _ in range(30):
            out = draw_overlay(img, None, snap)
            cv2.imencode(".jpg", cv2.cvtColor(cv2.cvtColor(out, cv2.COLOR_BGR2RGB), cv2.COLOR_RGB2BGR),
                         [cv2.IMWRITE_JPEG_QUALITY, 80])
        server_ms = (time.perf_counter() - t0) / 30 * 1000
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; server-side draw+JPEG "
          f"{server_ms:.1f} ms/frame")
    print(f"1280x720 frames to headless chromium, {secs:.0f} s per row (target >= 20 fps, < 100 ms)")
    print(f"{'path':40s} {'fps':>6s} {'lat med ms':>11s} {'lat p95 ms':>11s} {'shown/pushed':>13s}")
    for name, r in rows:
        print(f"{name:40s} {r['fps']:6.1f} {r['lat_median']:11.1f} {r['lat_p95']:11.1f} {r['frames']:6d}/{r['pushed']:<6d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
