"""Alarms with a meaning (issue 33 item 4): alarm episodes in a real-clock session on a busy machine.

    PYTHONPATH=app python benchmarks/alarm_episodes.py [--seconds N] [--hogs N] [--json] [--baseline REF]

Runs the web app's engine (clock="real": the rendered simulated camera in its own process,
registration, control process, engine thread; as ``monotracker serve`` runs it) with a still head,
tracking, ``--hogs`` CPU hogs (busy loops, ``_hogs.py``) beside it, nothing injected: a healthy
camera on a busy machine. For each alarm code it counts the board's *episodes* (what the operator
sees as "xN") and the alerts written to the audit log, per minute of tracking, and the
TRACKING<->HOLDING changes of the arm (the robot's own 0.1 s freshness rule: unchanged here).

The baseline runs in the same invocation under the same hogs, one after the other: the code of git
ref ``--baseline`` (default ``main``), exported to a temporary folder and run in a child process
with its ``app/`` on PYTHONPATH; then this checkout. Goal (issue 33): no ``camera_freeze`` at
all, no condition raised more than once a minute. The last line is JSON with ``--json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def run_session(seconds: float, camera: str) -> dict:
    """One tracking session of ``seconds`` (wall s) with the code on PYTHONPATH; episode counts."""
    from monotracker.engine import Session, SessionConfig
    from monotracker.sim.phantom import default_phantom

    with tempfile.TemporaryDirectory(prefix="alarm-episodes-") as home:
        s = Session(SessionConfig(home=Path(home), clock="real", camera=camera, trajectory="still"))
        try:
            s.start()
            ph = default_phantom()
            for c in ph.fiducial_centres_lps:
                assert s.add_fiducial(c, ph.fiducial_radius_mm).ok
            assert s.confirm_fiducials().ok and s.use_sample_plan().ok
            assert s.start_camera().ok
            t_end = time.monotonic() + 120.0
            while not (s.arm("1234").ok and s.start_tracking().ok):  # first lock on a loaded machine
                if time.monotonic() > t_end:
                    return {"error": "never started tracking"}
                time.sleep(0.2)
            board = s._alarms.board
            ep0 = dict(board._episodes)
            n_audit0 = len(s.audit_entries())
            states, frames0 = [], s.snapshot().camera.frames
            t0 = time.monotonic()
            while time.monotonic() - t0 < seconds:
                states.append(s.snapshot().robot.state)
                time.sleep(0.02)
            minutes = (time.monotonic() - t0) / 60.0
            snap = s.snapshot()
            episodes = {c: n - ep0.get(c, 0) for c, n in board._episodes.items() if n - ep0.get(c, 0)}
            rows = [r for r in s.audit_entries()[n_audit0:] if r.kind == "alert"]
        finally:
            s.shutdown()
    alerts: dict[str, int] = {}
    for r in rows:
        alerts[r.code] = alerts.get(r.code, 0) + 1
    flips = sum(1 for a, b in zip(states, states[1:]) if a != b and {a, b} <= {"tracking", "holding"})
    return {"minutes": minutes, "episodes": episodes, "alerts": alerts,
            "flips_per_min": flips / minutes, "holding_share": sum(st == "holding" for st in states) / max(1, len(states)),
            "fps": (snap.camera.frames - frames0) / (60.0 * minutes), "active_at_end": [a.code for a in snap.alarms]}


def export_ref(ref: str, dest: Path) -> Path:
    """``app/`` of git ref ``ref`` exported under ``dest``; returns the folder to put on PYTHONPATH."""
    tar = dest / "app.tar"
    with open(tar, "wb") as f:
        subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", ref, "app"], stdout=f, check=True)
    with tarfile.open(tar) as t:
        t.extractall(dest, filter="data")
    return dest / "app"


def child(name: str, app: Path, seconds: float, camera: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(app))
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", "--seconds", str(seconds),
                          "--camera", camera], env=env, capture_output=True, text=True, cwd=ROOT)
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        return {"name": name, "error": (out.stderr.strip().splitlines() or ["no output"])[-1]}
    return {"name": name, **json.loads(lines[-1])}


def _per_min(r: dict, key: str) -> dict:
    return {c: round(n / r["minutes"], 2) for c, n in sorted(r[key].items())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=600.0, help="tracking time per run, s (default 600: the issue's 10 min)")
    ap.add_argument("--hogs", type=int, default=4, help="CPU hogs beside the session (default 4)")
    ap.add_argument("--camera", default="sim", help="sim (rendered, default) or sim-points")
    ap.add_argument("--baseline", default="main", help="git ref of the baseline (default main); '' for none")
    ap.add_argument("--json", action="store_true", help="last line: the results as JSON")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if not (args.seconds > 0) or args.hogs < 0:
        ap.error("--seconds must be positive and --hogs at least 0")
    if args.child:
        print(json.dumps(run_session(args.seconds, args.camera)))
        return 0
    from _hogs import hogs

    results = []
    with tempfile.TemporaryDirectory(prefix="alarm-episodes-base-") as tmp, hogs(args.hogs):
        time.sleep(1.0)
        load = os.getloadavg()[0]
        print(f"# {args.hogs} CPU hogs, load average {load:.1f} at the start, {args.seconds:.0f} s tracking per run, "
              f"camera {args.camera}, {os.cpu_count()} CPUs", flush=True)
        runs = []
        if args.baseline:
            try:
                runs.append((f"baseline ({args.baseline})", export_ref(args.baseline, Path(tmp))))
            except (subprocess.CalledProcessError, OSError) as exc:
                print(f"# baseline {args.baseline!r} not exported: {exc}")
        runs.append(("this checkout", ROOT / "app"))
        for name, app in runs:
            r = child(name, app, args.seconds, args.camera)
            results.append(r)
            if "error" in r:
                print(f"{name}: {r['error']}", flush=True)
                continue
            worst = max(r["episodes"].values(), default=0) / r["minutes"]
            print(f"{name}: {r['minutes']:.1f} min, {r['fps']:.1f} fps, arm tracking<->holding "
                  f"{r['flips_per_min']:.1f}/min, holding {100 * r['holding_share']:.0f} %", flush=True)
            print(f"  episodes/min: {_per_min(r, 'episodes') or 'none'}  (worst {worst:.2f}/min)")
            print(f"  alerts/min:   {_per_min(r, 'alerts') or 'none'}")
            print(f"  camera_freeze episodes: {r['episodes'].get('camera_freeze', 0)}; active at the end: "
                  f"{r['active_at_end'] or 'none'}", flush=True)
        end_load = os.getloadavg()[0]
    print(f"# load average {end_load:.1f} at the end")
    if args.json:
        print(json.dumps({"hogs": args.hogs, "seconds": args.seconds, "load_start": load, "load_end": end_load,
                          "runs": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
