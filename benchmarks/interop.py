"""Interop benchmark: OpenIGTLink stream rate and latency on the wall clock, recording and replay.

Usage: PYTHONPATH=app python benchmarks/interop.py [--quick] [--camera sim|sim-points] [--json]

Table 1, OpenIGTLink (real-clock session, as ``monotracker serve --igtl-port``): a pyigtl client
on 127.0.0.1 receives for a window of W seconds; rates of ``CTToCamera`` / ``Status`` messages
received per wall second, and capture -> receipt latency (ms). Baseline measured in the same run:
the camera's own rate (estimates the engine handled per second in the same window): the stream
can only be as fast as the camera, and should be exactly that fast. Goal: >= 20 Hz (issue 29: >= 28
Hz with the sim camera). The arm is armed and tracking the sample path in the window, so
``NeedleTipToCT`` (sent with every fresh trusted pose while the arm's tip is known) is counted too.

Table 2, recording and replay (simulated clock, rendered twin): frames recorded, MB per frame,
wall time of the recorded run vs the same run without recording (baseline, same run), replay
time per frame and ``max_pose_diff_mm``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _plan_home(root: Path) -> Path:
    from monotracker.engine import Session, SessionConfig
    from monotracker.sim.phantom import default_phantom

    home = root / "planned"
    s = Session(SessionConfig(home=home, clock="sim"))
    ph = default_phantom()
    for c in ph.fiducial_centres_lps:
        s.add_fiducial(c, ph.fiducial_radius_mm)
    s.confirm_fiducials()
    s.use_sample_plan()
    s.shutdown()
    return home


def _fresh(planned: Path, root: Path, name: str) -> Path:
    h = root / name
    h.mkdir()
    shutil.copy(planned / "plan.json", h / "plan.json")
    return h


#: the benchmark session's arming PIN (its own temporary home)
PIN = "1234"


def bench_igtl(planned: Path, root: Path, camera: str, window_s: float) -> dict:
    import pyigtl

    from monotracker.engine import Session, SessionConfig
    from monotracker.interop.igtl import IGTLStreamer

    s = Session(SessionConfig(home=_fresh(planned, root, f"igtl-{camera}"), camera=camera, clock="real",
                              arm_pin=PIN))
    got = []
    lock = threading.Lock()
    handled = []

    class _Log(dict):
        def __setitem__(self, k, m):
            with lock:
                got.append((time.time(), m))
            super().__setitem__(k, m)

    port = _free_port()
    st = IGTLStreamer(s, port)
    client = None
    try:
        s.start()
        st.start()
        s.add_pose_listener(lambda smp, trusted, now: handled.append(time.monotonic()))
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", port, start_now=False)
        client.incoming_messages = _Log()
        client.start()
        s.start_camera()
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # warm-up: first trusted pose
            p = s.snapshot().pose
            if p is not None and p.trusted:
                break
            time.sleep(0.05)
        # the arm tracking the path: NeedleTipToCT goes out only then (the tip joined to the pose)
        tracking = s.arm(PIN).ok and s.start_tracking().ok
        while tracking and time.monotonic() < deadline and s.snapshot().robot.state != "tracking":
            time.sleep(0.05)
        with lock:
            got.clear()
        n0 = len(handled)
        t0 = time.monotonic()
        time.sleep(window_s)
        with lock:
            rows = list(got)
        dt = time.monotonic() - t0
        cam_hz = (len(handled) - n0) / dt
    finally:
        if client is not None:
            client.stop()
        st.stop()
        s.shutdown()
    cam = [(t, m) for t, m in rows if m.device_name == "CTToCamera"]
    tip = [m for _, m in rows if m.device_name == "NeedleTipToCT"]
    status = [m for _, m in rows if m.device_name == "Status"]
    lat = [1000 * (t - m.timestamp) for t, m in cam]
    return {"camera": camera, "window_s": dt, "camera_hz_baseline": cam_hz, "ct_to_camera_hz": len(cam) / dt,
            "status_hz": len(status) / dt, "needle_tip_hz": len(tip) / dt,
            "needle_tip_stamps_unique": len({m.timestamp for m in tip}) == len(tip), "arm_tracking": tracking,
            "latency_ms_median": float(np.median(lat)) if lat else None,
            "latency_ms_p95": float(np.percentile(lat, 95)) if lat else None}


def bench_recording(planned: Path, root: Path, seconds: float) -> dict:
    from monotracker.demo.run import DemoOptions, run_demo
    from monotracker.interop.replay import replay_recording

    t = time.perf_counter()
    run_demo(DemoOptions(seconds=seconds, home=_fresh(planned, root, "norec")))
    base = time.perf_counter() - t
    rec = root / "rec"
    t = time.perf_counter()
    r = run_demo(DemoOptions(seconds=seconds, home=_fresh(planned, root, "rec-home"), record=rec))
    with_rec = time.perf_counter() - t
    m = json.loads((rec / "manifest.json").read_text())
    size = sum(p.stat().st_size for p in (rec / "frames").glob("*.png"))
    t = time.perf_counter()
    rep = replay_recording(rec)
    rt = time.perf_counter() - t
    return {"seconds": seconds, "frames": m["frames"], "mb_per_frame": size / 1e6 / max(1, m["frames"]),
            "run_wall_s_baseline": base, "run_wall_s_recording": with_rec, "recording_ok": r["recording"]["ok"],
            "replay_s_per_frame": rt / max(1, m["frames"]), "replay_frames": rep.frames,
            "max_pose_diff_mm": rep.max_pose_diff_mm}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="short windows")
    ap.add_argument("--camera", default=None, help="sim | sim-points (default: both; --quick: sim-points)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    cams = [a.camera] if a.camera else (["sim-points"] if a.quick else ["sim-points", "sim"])
    window = 5.0 if a.quick else 15.0
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="interop-bench-") as tmp:
        root = Path(tmp)
        planned = _plan_home(root)
        igtl = [bench_igtl(planned, root, c, window) for c in cams]
        rec = bench_recording(planned, root, 2.0 if a.quick else 4.0)
    if a.json:
        print(json.dumps({"load_1min": load, "igtl": igtl, "recording": rec}))
        return
    print(f"OpenIGTLink stream (real clock, pyigtl client on 127.0.0.1; load average {load:.1f} on "
          f"{os.cpu_count()} CPUs)")
    print(f"{'camera':<11} {'window s':>8} {'camera Hz (baseline)':>21} {'CTToCamera Hz':>14} {'Status Hz':>10} "
          f"{'NeedleTipToCT Hz':>16} {'latency ms med/p95':>19}")
    for r in igtl:
        lat = "-" if r["latency_ms_median"] is None else f"{r['latency_ms_median']:.0f} / {r['latency_ms_p95']:.0f}"
        print(f"{r['camera']:<11} {r['window_s']:>8.1f} {r['camera_hz_baseline']:>21.1f} {r['ct_to_camera_hz']:>14.1f} "
              f"{r['status_hz']:>10.1f} {r['needle_tip_hz']:>16.1f} {lat:>19}")
    print("\nRecording and replay (rendered twin, simulated clock)")
    print(f"  {rec['frames']} frames, {rec['mb_per_frame']:.2f} MB/frame (PNG); run wall {rec['run_wall_s_recording']:.1f} s "
          f"with recording vs {rec['run_wall_s_baseline']:.1f} s without (baseline)")
    print(f"  replay: {1000 * rec['replay_s_per_frame']:.0f} ms/frame, {rec['replay_frames']} poses compared, "
          f"max_pose_diff_mm {rec['max_pose_diff_mm']}")


if __name__ == "__main__":
    main()
