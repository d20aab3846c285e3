"""Overlay streaming to real headless browsers: frames per second per client and frame-to-screen
latency, with 1 or more clients (tabs) watching the live view at once.

    python benchmarks/web_overlay.py [--seconds 10] [--clients 3] [--hogs 4] [--quick]

The web app (MonoTrackerApp, every tab on its Register step) gets 1280x720 camera-like frames at
30 fps with a 20-bit frame number stamped in a corner. Debian's chromium (Playwright, headless,
one page per client) reads the number back from the live <img> on every animation frame and
notes Date.now(); latency = browser time seen - server time the frame was encoded (same clock).

Rows, measured in the same run:
* baseline (the per-client push before issue 14): the overlay drawn at 1280x720, then every
  client's image encoded from the full frame separately (N JPEG encodes of 1280x720 per frame);
* web app: the app's own overlay thread takes the newest camera frame, downscales it to the width shown,
  draws the overlay at that size and encodes it ONCE; the same bytes go to all, raw (not
  compressed again per tab); a frame is encoded only when some tab has taken the previous one
  (or 0.25 s passed). "shown/pushed": frames a page showed / frames encoded;
* baseline / web app + live sim camera: the same two, on the whole app's own frames (the
  simulated camera in its own process, detection and registration at their raised priority, a
  planned session): what the overlay gets when the pose pipeline takes its share first.
The probe (the same for every row) notes the frame number when the live <img> has loaded a new
frame: by default from a JPEG comment the server adds (no second decode of the pixels on the
page's main thread; every 10th frame's barcode is read from the pixels too and must agree:
"pixel check"); ``--probe pixels`` reads every frame's barcode. After the table, the CPU use of
the server's threads and of the browsers' processes in each row's measured window
(``proc_cpu.py``), and with ``--idle-row`` what the open pages cost with nothing streamed.
The web app encodes once per width the tabs show the image at (``ui/stream.py``: 640 px for
these 1600 px wide pages), the baseline the full 1280x720 per tab.
Target (issue 14): >= 15 fps per client with 3 clients on a loaded machine (``--hogs 4``: four
busy loops at nice 0 beside the app and the browsers, ``_hogs.py``); >= 25 fps and <= 60 ms
median with one client on a quiet one.
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

from _hogs import hogs, planned_home

#: before any page script: remember the Blob behind every object URL (viser shows each frame as
#: an <img> with a blob: URL), so the probe can read the frame number from the JPEG's comment
#: without decoding pixels
INIT_JS = """
(() => { const blobs = new Map(); window.__mtBlobs = blobs; const make = URL.createObjectURL.bind(URL);
  URL.createObjectURL = (b) => { const u = make(b); if (b instanceof Blob && b.type === 'image/jpeg') { blobs.set(u, b);
    if (blobs.size > 64) blobs.delete(blobs.keys().next().value); } return u; }; })();
"""

#: the probe, on every animation frame: when the live <img> (as wide as the stream) shows a new frame
#: (a new blob URL, loaded) note Date.now() and the frame number. ``marker`` (default): the number
#: from the JPEG comment (reads 64 bytes; the browser decodes the pixels once, for the screen, as
#: it would with no probe); ``pixels``: the barcode read from the pixels (drawImage + getImageData
#: decodes every frame a second time on the page's main thread: about a third of the page's CPU).
#: With ``marker`` every 10th frame's barcode is read as well and must agree (``check``).
JS = """
([mode, w]) => { window.__seen = []; window.__check = [0, 0]; const c = document.createElement('canvas');
  const ctx = c.getContext('2d', {willReadFrequently: true});
  let last = -1, lastSrc = '', k = 0;
  function pixels(im) { c.width = 320; c.height = 16;
    ctx.drawImage(im, 0, im.naturalHeight - 16, 320, 16, 0, 0, 320, 16);
    const d = ctx.getImageData(0, 0, 320, 16).data; let v = 0;
    for (let b = 0; b < 20; b++) { const x = b * 16 + 8, y = 8; const q = (y * 320 + x) * 4;
      v = (v << 1) | ((d[q] + d[q+1] + d[q+2]) / 3 > 127 ? 1 : 0); }
    return v; }
  function seen(v, t) { if (v !== last) { last = v; window.__seen.push([v, t]); } }
  function tick() {
    // the live view: the <img> as wide as the stream (a loaded CT's slice images are others)
    const imgs = [...document.querySelectorAll('img')].filter(i => i.naturalWidth === w);
    if (imgs.length && imgs[0].src !== lastSrc && imgs[0].complete) { const im = imgs[0]; lastSrc = im.src;
      const t = Date.now(); const blob = window.__mtBlobs && window.__mtBlobs.get(im.src);
      if (mode === 'pixels' || !blob) { seen(pixels(im), t); }
      else { const vp = (k++ % 10 === 0) ? pixels(im) : null;
        blob.slice(0, 64).arrayBuffer().then(buf => {
          const s = new TextDecoder('latin1').decode(buf); const m = s.match(/MTFRAME (\\d+)/);
          if (!m) return; const v = parseInt(m[1]); seen(v, t);
          if (vp !== null) { window.__check[0]++; if (vp === v) window.__check[1]++; } }); } }
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


def run(seconds: float, shared: bool, clients: int, display_width: int = 960, live_camera: bool = False,
        idle: bool = False, probe: str = "marker"):
    """One row: ``clients`` pages watch for ``seconds``; returns (per-client fps and latency, CPU
    use (:func:`proc_cpu.cpu_use`) in the measured window). With ``live_camera`` the frames are
    the whole app's own: the simulated camera (its own process), detection and registration at
    their priorities, as in the OR. ``idle``: no frames at all (what the pages, the server and the
    browsers cost with nothing streamed). ``probe``: see :data:`JS`."""
    import socket

    import cv2
    from playwright.sync_api import sync_playwright

    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp
    from monotracker.ui.overlay import draw_overlay

    if live_camera:
        s = Session(SessionConfig(home=planned_home("web-overlay-"), camera="sim"))
        s.start()
        assert s.start_camera().ok
    else:
        s = Session(SessionConfig(home=Path(tempfile.mkdtemp())))
    with socket.socket() as so:
        so.bind(("127.0.0.1", 0))
        port = so.getsockname()[1]
    app = MonoTrackerApp(s, "127.0.0.1", port, stream_code=True, display_width=display_width)
    app.start()
    base = camera_like_frame()
    stop = threading.Event()
    newest = [None]
    if shared and not live_camera:  # the app's own overlay thread takes the newest frame, as from a camera
        s.latest_frame = lambda: newest[0]

    camera_frame = s.latest_frame
    if not shared:  # the per-client push below replaces the app's overlay thread
        s.latest_frame = lambda: None

    def pusher():
        i, last = 0, None
        while not stop.is_set() and not idle:
            t0 = time.monotonic()
            if live_camera:  # the newest frame the app's pipeline processed, each once
                fr = camera_frame()
                if fr is None or fr[1] == last:
                    stop.wait(0.005)
                    continue
                img, last, est = fr
            else:
                img, est = np.roll(base, i * 7, axis=1), None
                i += 1
            if shared:
                newest[0] = (img, i, None)
            else:  # the per-client push: full-size frame, one encode per client
                out = draw_overlay(img, est, s.snapshot())
                with app.stream._lock:
                    app.stream.count += 1
                    n = app.stream.count
                strip = frame_code_strip(n)
                out[-strip.shape[0]:, :strip.shape[1]] = strip
                app.stream.pushed[n] = time.time()
                rgb = cv2.cvtColor(out, cv2.COLOR_BGR2RGB)
                for v in app.views():  # what `h_live.image = rgb` did: viser's encode, per tab
                    h = v.live.h_img
                    fmt, data = _encode_image_binary(rgb, "jpeg")
                    h._format, h._data = fmt, with_frame_comment(data, n)
            if not live_camera:
                stop.wait(max(0.0, 1 / 30 - (time.monotonic() - t0)))

    from viser._scene_api import _encode_image_binary

    import proc_cpu
    from monotracker.ui.overlay import frame_code_strip
    from monotracker.ui.stream import with_frame_comment

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path="/usr/bin/chromium", headless=True,
                              args=["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                                    "--disable-component-update", "--disable-sync", "--no-first-run",
                                    "--disable-renderer-backgrounding", "--disable-background-timer-throttling",
                                    "--disable-backgrounding-occluded-windows"])
        pages = []
        for _ in range(clients):
            ctx = b.new_context(viewport={"width": 1600, "height": 1000})
            ctx.add_init_script(INIT_JS)
            page = ctx.new_page()
            page.goto(app.url)
            page.get_by_role("button", name="3 Register", exact=True).first.wait_for(timeout=120000)
            pages.append(page)
        t0 = time.monotonic()
        while len(app.views()) < clients and time.monotonic() - t0 < 120:
            time.sleep(0.2)
        for v in app.views():
            v.goto("register")
        th = threading.Thread(target=pusher, daemon=True)
        if not (shared and live_camera):  # there the app's own overlay thread does it all
            th.start()
        time.sleep(2.0)
        width = app.stream.width_for(app.views()[0].live_width) if shared else 1280  # of the live <img>
        for page in pages:
            page.evaluate(JS, [probe, width])
        cpu0, t_cpu0, w0 = proc_cpu.snapshot(), time.monotonic(), time.time()
        time.sleep(seconds)
        w1 = time.time()
        cpu = proc_cpu.cpu_use(cpu0, proc_cpu.snapshot(), time.monotonic() - t_cpu0)
        seen_all = [page.evaluate("window.__seen") for page in pages]
        checks = [page.evaluate("window.__check") for page in pages]
        stop.set()
        if th.is_alive():
            th.join(timeout=5)
        b.close()
    app.stop()
    s.shutdown()
    pushed = dict(app.stream.pushed)
    out = []
    for seen in seen_all:
        lat = [t_seen - pushed[v] * 1000 for v, t_seen in seen if v in pushed]
        n = len(seen)
        span = (seen[-1][1] - seen[0][1]) / 1000 if n > 1 else float("nan")
        out.append({"fps": (n - 1) / span if n > 1 else 0.0, "lat_median": float(np.median(lat)) if lat else float("nan"),
                    "lat_p95": float(np.percentile(lat, 95)) if lat else float("nan"), "frames": n,
                    "pushed": sum(w0 <= t <= w1 for t in pushed.values()), "frames_in": sum(w0 <= t <= w1 for _, t in
                                                                                               ((v, t / 1000) for v, t in seen))})
    for r, (n_checked, n_agree) in zip(out, checks):
        r["check"] = (n_checked, n_agree)
    return out, cpu


def main() -> int:
    import os

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--clients", type=int, default=1, help="browser tabs watching at once (default 1)")
    ap.add_argument("--quick", action="store_true", help="3 s per row")
    ap.add_argument("--hogs", type=int, default=0, help="CPU hogs beside app and browsers (default 0; 4: loaded)")
    ap.add_argument("--width", type=int, default=960, help="widest the shared stream is encoded (px, default 960)")
    ap.add_argument("--idle-row", action="store_true",
                    help="add a row with the same pages open and no frames streamed (the browsers' own floor)")
    ap.add_argument("--probe", choices=("marker", "pixels"), default="marker",
                    help="how pages read the frame number: JPEG comment (default) or pixels (decodes every frame twice)")
    ap.add_argument("--synthetic-only", action="store_true", help="leave out the two live-camera rows")
    a = ap.parse_args()
    secs = 3.0 if a.quick else a.seconds
    load = os.getloadavg()[0]
    kw = dict(clients=a.clients, probe=a.probe)
    with hogs(a.hogs):
        rows = [("pages open, nothing streamed", run(secs, True, idle=True, **kw))] if a.idle_row else []
        rows += [("baseline: per-client encode 1280x720", run(secs, False, **kw)),
                 ("web app: encode once per shown width", run(secs, True, display_width=a.width, **kw))]
        if not a.synthetic_only:
            rows += [("baseline + live sim camera, registration", run(secs, False, live_camera=True, **kw)),
                     ("web app + live sim camera, registration", run(secs, True, display_width=a.width,
                                                                     live_camera=True, **kw))]
        load_end = os.getloadavg()[0]
    print(f"machine: {os.cpu_count()} cores, {a.hogs} CPU hogs, load average {load:.1f} at start, {load_end:.1f} at end; "
          f"{a.clients} client(s), {secs:.0f} s per row, source 30 fps")
    print("target: >= 15 fps per client with 3 clients loaded; >= 25 fps, <= 60 ms median with 1 client quiet")
    print(f"probe: {a.probe}" + (" (frame number from the JPEG comment; 'pixel check': every 10th frame's "
                                 "barcode read from the pixels agrees)" if a.probe == "marker" else ""))
    print(f"{'path':42s} {'client':>6s} {'fps':>6s} {'lat med ms':>11s} {'lat p95 ms':>11s} {'shown/pushed':>13s}"
          f" {'pixel check':>12s}")
    print("(shown/pushed: frames a page showed / frames the server encoded, both in the measured window)")
    for name, (per, _cpu) in rows:
        for k, r in enumerate(per):
            chk = f"{r['check'][1]}/{r['check'][0]}" if a.probe == "marker" else "-"
            print(f"{name:42s} {k:6d} {r['fps']:6.1f} {r['lat_median']:11.1f} {r['lat_p95']:11.1f} "
                  f"{r['frames_in']:6d}/{r['pushed']:<6d} {chk:>12s}")
    print(f"\nCPU use during the measured window (cores; 1.0 = one core busy; the machine has {os.cpu_count()}):")
    for name, (_per, (by_class, by_thread)) in rows:
        cls = ", ".join(f"{k} {v:.2f}" for k, v in sorted(by_class.items(), key=lambda kv: -kv[1]) if v >= 0.005)
        thr = ", ".join(f"{k} {v:.2f}" for k, v in sorted(by_thread.items(), key=lambda kv: -kv[1]) if v >= 0.01)
        print(f"  {name}: {cls}\n    server threads: {thr}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
