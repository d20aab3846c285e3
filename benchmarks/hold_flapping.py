"""Does the tracking state flap under load? Hold/resume transitions per minute, threaded session.

    python benchmarks/hold_flapping.py [--quick] [--seconds S] [--hogs N]

Runs the web app's engine (clock="real": camera, registration, control and engine threads) on
the digital twin with a still head, ``N`` CPU hogs (busy loops, ``_hogs.py``) beside it,
and counts, while tracking: TRACKING<->HOLDING transitions, ``pose_stale`` and ``resumed`` audit
rows, Start-tracking refusals (one try every 0.5 s while not tracking), and the pose age at
arrival (capture -> the engine sees it). Each configuration in ``--configs`` runs in the same
invocation, one after the other on the same load: ``baseline`` is the loop without hysteresis
(``resume_dwell_s=0, start_wait_s=0``), ``hysteresis`` the defaults.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _hogs import hogs

from monotracker.engine import Session, SessionConfig
from monotracker.sim.phantom import default_phantom

CONFIGS = {
    "baseline": {"resume_dwell_s": 0.0, "start_wait_s": 0.0},
    "hysteresis": {},
    "before": {},  # the defaults, labelled for a run against an older checkout (PYTHONPATH=old/app)
}


def _plan(s: Session) -> None:
    ph = default_phantom()
    for c in ph.fiducial_centres_lps:
        assert s.add_fiducial(c, ph.fiducial_radius_mm).ok
    assert s.confirm_fiducials().ok and s.use_sample_plan().ok


def run_one(name: str, seconds: float, camera: str) -> dict:
    kw = CONFIGS[name]
    with tempfile.TemporaryDirectory(prefix="ops-flap-") as home:
        s = Session(SessionConfig(home=Path(home), clock="real", camera=camera, trajectory="still", **kw))
        ages: list[float] = []
        orig = s._loop.on_pose

        def on_pose(sample, now):  # measure only: the age the engine sees at arrival
            ages.append(now - sample.t_capture)
            orig(sample, now)

        s._loop.on_pose = on_pose
        try:
            s.start()
            _plan(s)
            assert s.start_camera().ok
            t_end = time.monotonic() + 60.0
            while not s.arm("1234").ok:  # arming needs a fresh trusted pose (newer engines)
                if time.monotonic() > t_end:
                    return {"name": name, "error": "never armed"}
                time.sleep(0.2)
            while not s.start_tracking().ok:  # first lock can take a while on a loaded machine
                if time.monotonic() > t_end:
                    return {"name": name, "error": "never started tracking"}
                time.sleep(0.2)
            # Start tracking as an operator would, every 0.5 s (stopping again at once)
            tries = refusals = 0
            t0 = time.monotonic()
            while time.monotonic() - t0 < seconds / 4:
                tries += 1
                if s.start_tracking().ok:
                    s.stop_tracking()
                else:
                    refusals += 1
                time.sleep(0.5)
            while not s.start_tracking().ok:
                time.sleep(0.1)
            n_audit0 = len(s.audit_entries())
            ages.clear()
            states, stale_pose_valid = [], 0
            t0 = time.monotonic()
            while time.monotonic() - t0 < seconds:
                snap = s.snapshot()
                states.append(snap.robot.state)
                if snap.robot.state == "holding" and snap.pose is not None and snap.pose.trusted \
                        and "stale" in (snap.robot.message or ""):
                    stale_pose_valid += 1  # the panel says VALID while the arm holds for staleness
                time.sleep(0.02)
            dur_min = (time.monotonic() - t0) / 60.0
            rows = s.audit_entries()[n_audit0:]
        finally:
            s.shutdown()
    flips = sum(1 for a, b in zip(states, states[1:]) if a != b and {a, b} <= {"tracking", "holding"})
    codes = [r.code for r in rows]
    ages_ms = 1000 * np.asarray(ages) if ages else np.array([np.nan])
    return {
        "name": name, "minutes": dur_min, "flips_per_min": flips / dur_min,
        "pose_stale_per_min": codes.count("pose_stale") / dur_min, "resumed_per_min": codes.count("resumed") / dur_min,
        "holding_share": float(np.mean([st == "holding" for st in states])) if states else float("nan"),
        "poses_per_s": len(ages) / (60 * dur_min), "age_p50_ms": float(np.median(ages_ms)),
        "age_p95_ms": float(np.percentile(ages_ms, 95)), "age_over_150ms": float(np.mean(ages_ms > 150)),
        "start_refusals": f"{refusals}/{tries}", "stale_while_pose_valid": stale_pose_valid,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="20 s per configuration instead of 60 s")
    ap.add_argument("--seconds", type=float, default=None)
    ap.add_argument("--hogs", type=int, default=4, help="CPU hogs beside the session (default 4)")
    ap.add_argument("--camera", default="sim", help="sim (rendered, default) or sim-points")
    ap.add_argument("--configs", default="baseline,hysteresis")
    args = ap.parse_args()
    seconds = args.seconds or (20.0 if args.quick else 60.0)
    with hogs(args.hogs):
        time.sleep(1.0)
        with open("/proc/loadavg") as f:
            load = f.read().split()[0]
        print(f"# {args.hogs} CPU hogs, load average {load} when started, {seconds:.0f} s tracking each, camera {args.camera}")
        cols = ["name", "flips_per_min", "pose_stale_per_min", "resumed_per_min", "holding_share", "poses_per_s",
                "age_p50_ms", "age_p95_ms", "age_over_150ms", "start_refusals", "stale_while_pose_valid"]
        print(" | ".join(cols))
        for name in args.configs.split(","):
            r = run_one(name, seconds, args.camera)
            if "error" in r:
                print(f"{name} | {r['error']}")
                continue
            print(" | ".join(f"{r[c]:.2f}" if isinstance(r[c], float) else str(r[c]) for c in cols), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
