"""STOP latency in a real browser, with the camera, detection and tracking running: quiet and
with CPU hogs beside the app, ours and today's code (the baseline) in the same run.

Each configuration starts the app under test (``benchmarks/_stop_server.py``: a real-clock
session, the rendered twin camera at 30 fps, detection, registration, a breathing head, the
simulated UR10 in its control process, the web app) from a source tree (``--baseline-tree``: a
worktree of the commit before the change; ours: this checkout), opens it in Debian's chromium
(Playwright), and then, ``--presses`` times: the local operator arms and starts tracking
(Session API), the page waits until it shows TRACKING (or HOLDING: a late pose; or ARMED:
tracking refused for 15 s for want of a fresh pose, as happens beside 4 hogs; each row says
which), and STOP is pressed on the page, in turn
by a click on the STOP button and by a key (Space / Escape), each with and without a PIN pad
(a modal) open. A click is a mouse press at the STOP button's place on the screen, whatever
is on top of it (as a gloved finger does), not a click on the element.

Times (ms) from the press (the browser's own time stamp of the input event) to:

* ``ack``: the control process latched the stop and commanded the arm to stop (the time the
  control process itself gives its transition to ``estopped``);
* ``still``: the first control cycle at or after the stop whose published state has every joint
  slower than 1e-3 rad/s (a sampler reads the control process's shared state every 2 ms: up to
  a sampler's delay late under load; the arm's own deceleration is part of it; an arm that
  already stood still at the press gives ``ack``). ``arm`` is the fastest joint's speed
  (rad/s) in the last state before the stop: tracking a breathing head the arm moves slowly;
  on its first approach to the entry it moves fast;
* ``page``: the page's robot state block reads E-STOPPED (a MutationObserver in the page; the
  paint follows within a frame);
* ``held``: press -> its release (pointerup / keyup; viser's button and hotkeys act on the
  release, a click: Playwright sends the mouse's down and up as two commands, so under load a
  gap a finger's tap would also have);
* ``send``: press -> the first message the page hands on for its websocket after the press
  (viser's client keeps the socket in a web worker: the page's postMessage to it; the browser's
  own part: the STOP's message, unless another of the page's went first);
* ``read``: press -> viser's websocket consumer decoding the STOP's message on the server's
  event loop (the last message decoded before the handler ran);
* ``recv`` and ``latch``: ``ack`` split where the web server's STOP handler calls
  ``Session.request_estop`` (the app under test stamps it): press -> that call (the browser
  sending, the kernel, the server's event loop getting the CPU and the GIL) and that call -> the
  control process's latch (shared memory, its e-stop watcher waking); ``wake``: the engine's
  write of the stop into the control process's stop slot -> its latch (the control process
  alone, one monotonic clock).

A press counts as working when the page shows E-STOPPED within ``--press-timeout`` s; the p50 /
p99 / max are over working presses. A round where the page did not show the armed arm (TRACKING,
HOLDING or ARMED) within that time (the page starved before the press) is not pressed: column ``skip``. ``other`` measures the other controls under the same load:
after each STOP, a click on a PIN pad digit and a digit pressed by the keyboard (Enter on the
focused digit), press -> the pad's dot count changes on the page (a server round trip), p50 / p95.
``api`` is the no-browser case of the issue: ``Session.estop()`` called from another thread as
the web server's handler does: the call's own duration and the time until ``Session.snapshot()``
reads ``estopped``.

Goal (issue 34): with 4 hogs, press -> arm commanded to stop (``ack``) p99 <= 100 ms, press ->
page shows it p99 <= 300 ms, every press works with a modal open, other controls p95 <= 300 ms.

The last line is a JSON object with every row and the goal's figures.

    .venv/bin/python benchmarks/stop_latency.py [--hogs N] [--json] [--presses N]
        [--baseline-tree PATH] [--baseline-presses N] [--api-presses N] [--quick] [--only ours|baseline]

Run it under ``cpu --quiet`` (the machine to itself) and report the load it prints.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from _hogs import start_hogs, stop_hogs  # noqa: E402

PIN = "2468"
TAG = "@@stop-bench "  # _stop_server.py's protocol lines
KINDS = ("click", "key", "click+pad", "key+pad")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run"]

#: in the page: the press's own time stamp (capture listeners) and the moment a condition holds
INSTRUMENT = """
() => {
  if (window.__mt) return;
  const now = () => performance.timeOrigin + performance.now();
  window.__mt = {armed: false, press: null, shown: null, cond: null, sent: null, release: null};
  const onPress = (e) => { const m = window.__mt;
    if (m.armed && m.press === null) m.press = performance.timeOrigin + e.timeStamp; };
  const onRelease = (e) => { const m = window.__mt;
    if (m.armed && m.press !== null && m.release === null) m.release = performance.timeOrigin + e.timeStamp; };
  window.addEventListener('pointerup', onRelease, true);
  window.addEventListener('keyup', onRelease, true);
  // the first message the page hands on for its websocket after the press (viser's client keeps
  // the socket in a web worker: a postMessage to it; the STOP's, unless another message of the
  // page's happened to go first: then earlier than the STOP's)
  for (const [proto, key] of [[Worker.prototype, 'postMessage'], [WebSocket.prototype, 'send']]) {
    const orig = proto[key];
    proto[key] = function (...args) { const m = window.__mt;
      if (m.armed && m.press !== null && m.sent === null) m.sent = now();
      return orig.apply(this, args); };
  }
  window.addEventListener('pointerdown', onPress, true);
  window.addEventListener('keydown', onPress, true);
  const check = () => { const m = window.__mt;
    if (m.armed && m.shown === null && m.cond && m.cond()) m.shown = now(); };
  new MutationObserver(check).observe(document.body, {subtree: true, childList: true, attributes: true,
                                                      characterData: true});
}
"""
ARM_STOP = """
() => { const m = window.__mt; m.press = null; m.shown = null; m.sent = null; m.release = null; m.armed = true;
  m.cond = () => { const el = document.querySelector('#mt-robot-state');
                   return !!el && el.dataset.state === 'estopped'; }; }
"""
ARM_DOTS = """
(n) => { const m = window.__mt; m.press = null; m.shown = null; m.armed = true;
  m.cond = () => { const el = document.querySelector('#mt-pin-dots');
                   return !!el && Number(el.dataset.n) !== n; }; }
"""


def chromium_path() -> str:
    for c in (os.environ.get("MONOTRACKER_CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium")):
        if c and Path(c).exists():
            return c
    raise SystemExit("chromium not found: install Debian's chromium (apt-get install -y chromium)")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """``_stop_server.py`` from source tree ``tree`` (its ``app/`` first on the path)."""

    def __init__(self, tree: Path, label: str, log_dir: Path):
        self.label = label
        self.home = Path(tempfile.mkdtemp(prefix=f"stop-bench-{label}-"))
        self.port = free_port()
        env = dict(os.environ, PYTHONPATH=str(tree / "app"), MONOTRACKER_HOME=str(self.home))
        self.log = open(log_dir / f"server-{label}.log", "w")
        self.p = subprocess.Popen([sys.executable, str(HERE / "_stop_server.py"), str(self.home), str(self.port), PIN],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.log, text=True,
                                  env=env, cwd=str(tree))
        self.hello = self._read(300.0)
        if not self.hello.get("ok"):
            raise SystemExit(f"{label}: the app did not come up ({self.hello}); see {self.log.name}")
        self.url = self.hello["url"]

    def _read(self, timeout_s: float) -> dict:
        import select

        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            r, _, _ = select.select([self.p.stdout], [], [], 1.0)
            if r:
                line = self.p.stdout.readline()
                if not line:
                    raise SystemExit(f"{self.label}: the app ended; see {self.log.name}")
                if line.startswith(TAG):
                    return json.loads(line[len(TAG):])
                continue  # the app's own output (viser's banner)
            if self.p.poll() is not None:
                raise SystemExit(f"{self.label}: the app ended (exit {self.p.returncode}); see {self.log.name}")
        raise SystemExit(f"{self.label}: no answer from the app in {timeout_s:.0f} s; see {self.log.name}")

    def ask(self, timeout_s: float = 300.0, **msg) -> dict:
        self.p.stdin.write(json.dumps(msg) + "\n")
        self.p.stdin.flush()
        return self._read(timeout_s)

    def close(self) -> None:
        try:
            self.ask(cmd="quit", timeout_s=60.0)
        except (SystemExit, OSError, ValueError):
            pass
        try:
            self.p.wait(30)
        except subprocess.TimeoutExpired:
            self.p.kill()
            self.p.wait(10)
        self.log.close()
        shutil.rmtree(self.home, ignore_errors=True)


def _pad_open(page) -> bool:
    return page.locator("#mt-pin-dots").count() > 0 and page.locator("#mt-pin-dots").first.is_visible()


def _dots(page) -> int:
    return int(page.locator("#mt-pin-dots").first.get_attribute("data-n") or 0)


def _timed(page, arm_js: str, arg, act, timeout_ms: float) -> float | None:
    """Arm the page's probe, act, wait for the condition: press -> condition (ms) or None."""
    page.evaluate(arm_js, arg) if arg is not None else page.evaluate(arm_js)
    act()
    try:
        page.wait_for_function("window.__mt.shown !== null && window.__mt.press !== null", timeout=timeout_ms)
    except Exception:  # noqa: BLE001 - playwright's TimeoutError: the press did not show
        page.evaluate("() => { window.__mt.armed = false; }")
        return None
    m = page.evaluate("() => { window.__mt.armed = false; return [window.__mt.press, window.__mt.shown]; }")
    return m[1] - m[0]


def _page_state(page) -> str | None:
    return page.evaluate("() => { const el = document.querySelector('#mt-robot-state');"
                         " return el ? el.dataset.state : null; }")


def _open_pad(page) -> None:
    page.get_by_role("button", name="Take control (PIN)", exact=True).first.click()
    page.locator("#mt-pin-dots").first.wait_for(state="visible")


def _close_pad(page) -> None:
    if _pad_open(page):
        page.get_by_role("button", name="Cancel", exact=True).last.click()
        page.locator("#mt-pin-dots").first.wait_for(state="detached")


def press_stop(page, srv: Server, kind: str, i: int, timeout_s: float) -> dict:
    """One STOP press of ``kind``; every time in ms from the press (None: did not happen)."""
    r = srv.ask(cmd="prepare")
    row = {"kind": kind, "prepared": bool(r.get("ok"))}
    if not r.get("ok"):
        row["error"] = f"could not start tracking: {r}"
        return row
    try:  # the state prepare reached: tracking, holding (a late pose) or armed (tracking refused)
        page.wait_for_function("document.querySelector('#mt-robot-state') && "
                               "['tracking', 'holding', 'armed'].includes("
                               "document.querySelector('#mt-robot-state').dataset.state)",
                               timeout=timeout_s * 1000)
    except Exception:  # noqa: BLE001 - playwright's TimeoutError: recorded, not a crash
        row["error"] = f"the page did not show TRACKING/HOLDING/ARMED in {timeout_s:.0f} s (shows {_page_state(page)!r})"
        return row
    row["state_at_press"] = _page_state(page)
    if kind.endswith("+pad"):
        _open_pad(page)
    box = page.get_by_role("button", name="STOP", exact=True).first.bounding_box()
    srv.ask(cmd="arm_measure")
    page.evaluate(ARM_STOP)
    t_py = time.time()
    if kind.startswith("click"):
        page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    else:
        page.keyboard.press("Space" if i % 2 == 0 else "Escape")
    try:
        page.wait_for_function("window.__mt.shown !== null", timeout=timeout_s * 1000)
        shown = True
    except Exception:  # noqa: BLE001 - playwright's TimeoutError
        shown = False
    m = page.evaluate("() => { window.__mt.armed = false; return [window.__mt.press, window.__mt.shown, window.__mt.sent, window.__mt.release]; }")
    wait_s = 30.0 if shown else 2.0  # how long the app waits for the stop's times
    res = srv.ask(cmd="result", wait_s=wait_s, timeout_s=wait_s + 60.0)
    press_ms = m[0] if m[0] is not None else 1000 * t_py
    row["worked"] = shown
    row["page_ms"] = (m[1] - press_ms) if shown and m[1] is not None else None
    def ms(later, earlier):  # app times are s, page times ms; None when either is unknown
        return None if later is None or earlier is None else later - earlier

    app = {k: (None if res.get(k) is None else 1000 * res[k])      # ms
           for k in ("ack_t", "still_t", "recv_t", "sock_t", "signal_t")}
    row["ack_ms"] = ms(app["ack_t"], press_ms)
    row["still_ms"] = ms(app["still_t"], press_ms)
    # the press split at the server's STOP handler: browser -> handler, handler -> the latch
    row["recv_ms"] = ms(app["recv_t"], press_ms)
    row["read_ms"] = ms(app["sock_t"], press_ms)    # press -> viser read it
    row["send_ms"] = ms(m[2], press_ms)             # press -> the page's websocket send
    row["held_ms"] = ms(m[3], press_ms)             # press -> release (pointerup / keyup)
    row["wake_ms"] = ms(app["ack_t"], app["signal_t"])
    row["latch_ms"] = ms(app["ack_t"], app["recv_t"])
    row["py_skew_ms"] = press_ms - 1000 * t_py  # browser stamp - harness send time (sanity)
    row["speed_rad_s"] = res.get("speed_rad_s")  # the arm's fastest joint just before the stop
    return row


def other_controls(page, timeout_s: float) -> dict:
    """With the pad open: a click on digit 1 and Enter on the focused digit 2: press -> dots."""
    out = {}
    if not _pad_open(page):
        _open_pad(page)
    n = _dots(page)
    b1 = page.get_by_role("button", name="1", exact=True).last.bounding_box()
    out["click_ms"] = _timed(page, ARM_DOTS, n, lambda: page.mouse.click(b1["x"] + b1["width"] / 2,
                                                                        b1["y"] + b1["height"] / 2), timeout_s * 1000)
    n = _dots(page)
    page.get_by_role("button", name="2", exact=True).last.focus()
    out["key_ms"] = _timed(page, ARM_DOTS, n, lambda: page.keyboard.press("Enter"), timeout_s * 1000)
    _close_pad(page)
    return out


def pct(a, q) -> float:
    a = [x for x in a if x is not None]
    return float(np.percentile(a, q)) if a else float("nan")


def run_config(browser, tree: Path, label: str, hogs: int, presses: int, api_presses: int, timeout_s: float,
               log_dir: Path, cap_s: float) -> dict:
    print(f"[{time.strftime('%H:%M:%S')}] {label}, {hogs} hogs: starting the app", flush=True)
    srv = Server(tree, f"{label}-{hogs}hogs", log_dir)
    procs = []
    rows, others, api = [], [], []
    t_start = time.monotonic()
    try:
        page = browser.new_page(viewport={"width": 1600, "height": 1000})
        page.set_default_timeout(timeout_s * 1000)
        page.goto(srv.url)
        page.locator("#mt-robot-state").first.wait_for()
        page.evaluate(INSTRUMENT)
        procs = start_hogs(hogs) if hogs else []
        load0 = os.getloadavg()[0]
        for i in range(presses):
            if time.monotonic() - t_start > cap_s:
                print(f"  run cap {cap_s:.0f} s reached after {i} presses", flush=True)
                break
            kind = KINDS[i % len(KINDS)]
            row = press_stop(page, srv, kind, i // len(KINDS), timeout_s)
            rows.append(row)
            sp = row.get("speed_rad_s")
            print(f"  press {i + 1:2d} {kind:9s} worked={row.get('worked')} ack={_f(row.get('ack_ms'))} "
                  f"still={_f(row.get('still_ms'))} page={_f(row.get('page_ms'))} ms; arm at "
                  f"{'-' if sp is None else f'{sp:.3f}'} rad/s, from {row.get('state_at_press', '-')}"
                  + (f"; {row['error']}" if row.get("error") else ""), flush=True)
            if row.get("worked"):
                try:
                    others.append(other_controls(page, timeout_s))
                except Exception as exc:  # noqa: BLE001 - a control that did not answer: recorded
                    others.append({"error": f"{type(exc).__name__}"})
            else:
                _close_pad(page)
        for _ in range(api_presses):
            if not srv.ask(cmd="prepare").get("ok"):
                continue
            api.append(srv.ask(cmd="api_press"))
        load1 = os.getloadavg()[0]
        page.close()
    finally:
        stop_hogs(procs)
        srv.close()
    return summarise(label, hogs, rows, others, api, srv.hello.get("control", ""), (load0, load1),
                     time.monotonic() - t_start)


def _f(v) -> str:
    return "-" if v is None else f"{v:.0f}"


def summarise(label, hogs, rows, others, api, control, load, wall_s) -> dict:
    out = {"tree": label, "hogs": hogs, "load_1min": list(load), "wall_s": wall_s, "control": control,
           "presses": rows, "other": others, "api": api, "by_kind": {}}
    for kind in KINDS + ("all",):
        sel = [r for r in rows if (kind == "all" or r["kind"] == kind) and "worked" in r]  # pressed
        ok = [r for r in sel if r.get("worked")]
        d = {"n": len(sel), "worked": len(ok),
             "not_pressed": len([r for r in rows if (kind == "all" or r["kind"] == kind) and "worked" not in r]),
             "arm_rad_s_p50": pct([r.get("speed_rad_s") for r in ok], 50)}
        for k in ("ack_ms", "still_ms", "page_ms", "held_ms", "send_ms", "read_ms", "recv_ms", "latch_ms", "wake_ms"):
            v = [r[k] for r in ok if r.get(k) is not None]
            d[k] = {"p50": pct(v, 50), "p99": pct(v, 99), "max": max(v) if v else float("nan"), "n": len(v)}
        out["by_kind"][kind] = d
    for k in ("click_ms", "key_ms"):
        v = [o.get(k) for o in others]
        out[f"other_{k}"] = {"p50": pct(v, 50), "p95": pct(v, 95), "n": len([x for x in v if x is not None]),
                             "missed": len([x for x in v if x is None])}
    for k in ("call_ms", "snapshot_ms"):
        v = [a.get(k) for a in api]
        out[f"api_{k}"] = {"p50": pct(v, 50), "p99": pct(v, 99), "max": max([x for x in v if x is not None],
                                                                             default=float("nan"))}
    return out


P3 = ("p50", "p99", "max")


def _qs(d: dict, *qs: str) -> str:
    """``d``'s quantiles ``qs`` (ms) as "a/b/c", "-" for none."""
    return "/".join(_f(None if np.isnan(d[q]) else d[q]) for q in qs)


def table(results: list[dict]) -> str:
    lines = [f"{'tree':9s} {'hogs':>4s} {'press':9s} {'works':>6s} {'skip':>4s} | {'ack p50/p99/max':>17s} | "
             f"{'still p50/p99/max':>17s} | {'page p50/p99/max':>18s} | arm rad/s p50 | "
             f"{'held p50/p99/max':>16s} | {'send p50/p99/max':>16s} | {'read p50/p99/max':>16s} | "
             f"{'recv p50/p99/max':>16s} | "
             f"{'latch p50/p99/max':>17s} | {'wake p50/p99/max':>16s}"]
    for r in results:
        for kind in KINDS + ("all",):
            d = r["by_kind"][kind]
            lines.append(f"{r['tree']:9s} {r['hogs']:4d} {kind:9s} {d['worked']:2d}/{d['n']:<3d} {d['not_pressed']:4d} | {_qs(d['ack_ms'], *P3):>17s} | "
                         f"{_qs(d['still_ms'], *P3):>17s} | {_qs(d['page_ms'], *P3):>18s} | "
                         f"{'-' if np.isnan(d['arm_rad_s_p50']) else format(d['arm_rad_s_p50'], '.3f'):>13s} | "
                         f"{_qs(d['held_ms'], *P3):>16s} | {_qs(d['send_ms'], *P3):>16s} | "
                         f"{_qs(d['read_ms'], *P3):>16s} | {_qs(d['recv_ms'], *P3):>16s} | "
                         f"{_qs(d['latch_ms'], *P3):>17s} | {_qs(d['wake_ms'], *P3):>16s}")
    lines.append("")
    lines.append(f"{'tree':9s} {'hogs':>4s} | other click p50/p95 | other key p50/p95 | api call p50/p99/max | "
                 f"api snapshot p50/p99/max | load 1-min")
    for r in results:
        oc, ok_, ac, asn = r["other_click_ms"], r["other_key_ms"], r["api_call_ms"], r["api_snapshot_ms"]
        g = _qs
        miss = oc["missed"] + ok_["missed"]
        lines.append(f"{r['tree']:9s} {r['hogs']:4d} | {g(oc, 'p50', 'p95'):>19s} | {g(ok_, 'p50', 'p95'):>17s} | "
                     f"{g(ac, 'p50', 'p99', 'max'):>20s} | {g(asn, 'p50', 'p99', 'max'):>24s} | "
                     f"{r['load_1min'][0]:.1f} -> {r['load_1min'][1]:.1f}"
                     + (f" ({miss} other presses never answered)" if miss else ""))
    return "\n".join(lines)


def _clean(o):
    """JSON-ready: NaN -> None."""
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, float) and not np.isfinite(o):
        return None
    return o


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hogs", type=int, default=4, help="CPU hogs beside the app in the loaded runs (default 4)")
    ap.add_argument("--presses", type=int, default=50, help="STOP presses per configuration (default 50)")
    ap.add_argument("--baseline-tree", type=Path, default=None,
                    help="a checkout of today's code (e.g. a worktree of the commit before the change)")
    ap.add_argument("--baseline-presses", type=int, default=None,
                    help="presses for the baseline (default: --presses); its slow presses may need fewer")
    ap.add_argument("--api-presses", type=int, default=10, help="Session.estop() presses without a browser (default 10)")
    ap.add_argument("--press-timeout", type=float, default=60.0, help="s a press may take to show (default 60)")
    ap.add_argument("--run-cap", type=float, default=1200.0, help="s at most per configuration (default 1200)")
    ap.add_argument("--only", choices=("ours", "baseline"), default=None)
    ap.add_argument("--no-quiet", action="store_true", help="only the loaded runs")
    ap.add_argument("--quick", action="store_true", help="8 presses, 3 API presses")
    ap.add_argument("--json", action="store_true", help="(the JSON line is always printed last)")
    args = ap.parse_args(argv)
    if args.hogs < 0 or args.presses < 1:
        ap.error("--hogs must be >= 0 and --presses >= 1")
    if args.baseline_tree is not None and not (args.baseline_tree / "app" / "monotracker").is_dir():
        ap.error(f"--baseline-tree {args.baseline_tree} is not a MonoTracker checkout (no app/monotracker)")
    if args.quick:
        args.presses, args.api_presses = 8, 3
    from playwright.sync_api import sync_playwright

    trees = []
    if args.only != "baseline":
        trees.append(("ours", ROOT, args.presses))
    if args.baseline_tree is not None and args.only != "ours":
        trees.insert(0, ("baseline", args.baseline_tree.resolve(), args.baseline_presses or args.presses))
    loads = ([] if args.no_quiet else [0]) + ([args.hogs] if args.hogs else [])
    log_dir = Path(tempfile.mkdtemp(prefix="stop-bench-logs-"))
    print(f"uptime before: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}", flush=True)
    results = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium_path(), headless=True, args=CHROMIUM_ARGS)
        try:
            for hogs in loads:
                for label, tree, n in trees:
                    results.append(run_config(browser, tree, label, hogs, n, args.api_presses, args.press_timeout,
                                              log_dir, args.run_cap))
        finally:
            browser.close()
    print(f"uptime after: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}", flush=True)
    print()
    print(table(results))
    goal = {}
    for r in results:
        if r["hogs"] == args.hogs and args.hogs:
            a = r["by_kind"]["all"]
            goal[r["tree"]] = {"ack_p99_ms": a["ack_ms"]["p99"], "page_p99_ms": a["page_ms"]["p99"],
                               "pad_presses_worked": sum(r["by_kind"][k]["worked"] for k in KINDS if k.endswith("+pad")),
                               "pad_presses": sum(r["by_kind"][k]["n"] for k in KINDS if k.endswith("+pad")),
                               "other_click_p95_ms": r["other_click_ms"]["p95"], "other_key_p95_ms": r["other_key_ms"]["p95"]}
    print(f"logs: {log_dir}")
    summary = {"goal": {"ack_p99_ms": 100, "page_p99_ms": 300, "other_p95_ms": 300, "hogs": args.hogs},
               "measured": goal, "rows": [{k: v for k, v in r.items() if k not in ("presses", "other", "api")}
                                          for r in results]}
    print(json.dumps(_clean(summary)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
