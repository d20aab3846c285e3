"""The pose pipeline at camera rate (issue 29 item 4): per stage, per frame, and the closed loop's
rate, pose age and tracking, this checkout against a baseline commit in the same run, quiet and
with 4 CPU hogs beside it (a neighbour's load: the 4 loops in a session of their own,
``_hogs.py``).

Per stage (median / p99 ms, wall time, one frame at a time on one thread): ``read`` (the frame
handed over: a copy of the image), ``hint`` (the balls' predicted ellipses), ``average`` (the
mean of a still view's frames the detector reads, ``vision/still_frames.py``; 0 in a tree
without it), ``detect``,
``register``, ``screen`` (the moved-fiducial test), ``gates`` (the checks after the
registration), ``motion`` (the camera-motion watch, where the tree's tracker times it apart),
``other`` (the rest of the tracker's frame: size and grayscale checks, and the camera-motion watch
in a tree that does not time it apart), ``publish`` (the estimate to the engine's
sample), ``after`` (work after the pose is given out, not in the pose's time: a due frame's
camera-motion check in a tree whose rigs defer it, ``PoseTracker.after_publish``; a tree without
it checks inline, in ``motion``); on photo-like frames of our simulator (9 balls, breathing head) at 1280x720 with balls
of 8, 13 and 20 px (radius) and at 1920x1080 with 20 px balls. Rendering is not timed. ``detect_register`` =
hint + average + detect + register + screen + gates (issue 29's budget: <= 10 ms median, <= 16 ms p99 at
720p, <= 20 ms at 1080p).

Closed loop: the headless demo (``monotracker demo --headless``: simulated clock, the twin camera
30 fps, the simulated UR10, the sample plan) with the still and breathing heads: frames/s,
share of control ticks tracking after the first lock, capture -> command latency, pose age
(newest trusted pose, every control tick), detection + registration per frame and the whole
estimate's compute (what the simulated clock charges a frame: its thread CPU time). The
simulated clock charges CPU time, not wall time: 4 hogs show up only through the CPU they take
from the caches and the core's frequency; a real-clock figure under hogs needs the web app's
threads (``benchmarks/pose_latency.py``).

Trees: this checkout, and :data:`BASELINE` (default: the main commit this work started from),
exported with ``git archive`` into a temporary folder; each runs ``_pose_rate_child.py`` in its
own process with its own ``app`` on PYTHONPATH.

Usage: ``/work/bin/cpu --quiet .venv/bin/python benchmarks/pose_rate.py [--quick] [--json]
[--baseline COMMIT] [--head still] [--average N]``; the last line is JSON with
``detect_register_ms_median`` (720p, worst ball size), ``fps``, ``tracking_fraction``
(breathing demo, quiet) for this checkout (and ``..._average`` for ``--average``), and every
figure of every tree. ``--average N`` adds this checkout with the opt-in still-view mean of N
frames (``TrackerConfig.average_still_frames``, ``SessionConfig.average_still_frames``): the
row "ours avg=N"; ``--head still`` streams a still head in the stage cases (the mean is then
kept and tested every frame, its dearest case; a breathing head restarts it at most frames).
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
REPO = HERE.parent
sys.path.insert(0, str(HERE))
#: the main commit issue 29's pipeline work of this round started from
BASELINE = "04b0986"


def export_tree(commit: str) -> Path | None:
    """``commit``'s ``app`` folder in a temporary folder (``git archive``), or None with the reason."""
    dest = Path(tempfile.mkdtemp(prefix=f"mt_pose_rate_{commit}_"))
    tar = dest / "tree.tar"
    try:
        with open(tar, "wb") as fh:
            subprocess.run(["git", "-C", str(REPO), "archive", commit, "app"], check=True, stdout=fh)
        with tarfile.open(tar) as tf:
            tf.extractall(dest, filter="data")
    except (OSError, subprocess.CalledProcessError, tarfile.TarError) as exc:
        print(f"(baseline {commit} not available: {exc})")
        return None
    return dest


def run_child(app: Path, home: Path, args, hogs: int, average: int = 0) -> dict | None:
    from _hogs import hogs as hog_procs

    env = dict(os.environ, PYTHONPATH=str(app))
    cmd = [sys.executable, str(HERE / "_pose_rate_child.py"), "--home", str(home), "--frames", str(args.frames),
           "--seconds", str(args.seconds), "--cases", args.cases, "--head", args.head]
    if average:
        cmd += ["--average", str(average)]
    with hog_procs(hogs):
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=str(REPO))
    if p.returncode != 0:
        print(f"  (failed: {p.stderr.strip().splitlines()[-1] if p.stderr.strip() else p.returncode})")
        return None
    return json.loads(p.stdout.strip().splitlines()[-1])


def _f(d, *keys, nd=1):
    for k in keys:
        if d is None:
            return "-"
        d = d.get(k)
    return "-" if d is None else f"{d:.{nd}f}"


def main(argv=None):
    from _hogs import planned_home

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames and shorter demos")
    ap.add_argument("--json", action="store_true", help="(the last line is JSON either way)")
    ap.add_argument("--baseline", default=BASELINE, help=f"baseline commit (default {BASELINE})")
    ap.add_argument("--no-hogs", action="store_true", help="quiet runs only")
    ap.add_argument("--head", default="breathing", choices=("breathing", "still"),
                    help="the stage cases' head (default breathing; still: what the still-view mean costs most)")
    ap.add_argument("--average", type=int, default=0, metavar="N",
                    help="also this checkout with the opt-in still-view mean of N frames "
                         "(TrackerConfig.average_still_frames; the row 'ours avg=N')")
    a = ap.parse_args(argv)
    a.frames, a.seconds = (60, 4.0) if a.quick else (150, 6.0)
    a.cases = "720:8,720:13,720:20,1080:20"
    print(f"pose rate: {a.frames} frames per stage case, {a.seconds:g} s demos; {os.cpu_count()} CPUs, "
          f"load {os.getloadavg()[0]:.2f} at the start (run it under `cpu --quiet`)")
    home = planned_home("mt_pose_rate_plan_")
    trees = [("ours", REPO / "app", 0)]
    if a.average:
        trees.append((f"ours avg={a.average}", REPO / "app", a.average))
    base = export_tree(a.baseline)
    if base is not None:
        trees.insert(0, (f"base {a.baseline}", base / "app", 0))
    results = {}
    for hogs in ((0,) if a.no_hogs else (0, 4)):
        for name, app, average in trees:
            t0 = time.time()
            print(f"  {name}, {hogs} hogs ...", flush=True)
            results[(name, hogs)] = run_child(app, home, a, hogs, average)
            print(f"    ({time.time() - t0:.0f} s, load {os.getloadavg()[0]:.2f})", flush=True)
    print(f"\nPer stage, ms median/p99 (wall, one thread), photo-like frames, {a.head} head:")
    stages = ("read", "hint", "average", "detect", "register", "screen", "gates", "motion", "other", "publish",
              "after", "detect_register")
    print(f"{'case':<14} {'tree':<13} {'hogs':>4} " + " ".join(f"{s[:9]:>11}" for s in stages)
          + f" {'trusted':>7} {'err px':>6}")
    for (name, hogs), r in results.items():
        if r is None:
            continue
        for case, st in r["stages"].items():
            cols = " ".join(f"{_f(st, s, 'p50', nd=2):>5}/{_f(st, s, 'p99', nd=1):>5}" for s in stages)
            print(f"{case:<14} {name:<13} {hogs:>4} {cols} {100 * st['trusted']:6.1f}% {st['centre_err_px'] or float('nan'):6.3f}")
    print("\nHeadless demo (simulated clock, 30 fps twin camera):")
    print(f"{'head':<10} {'tree':<13} {'hogs':>4} {'fps':>6} {'tracking':>8} {'lat p95':>7} {'age p50':>7} {'age p95':>7} "
          f"{'det+reg p50':>11} {'compute p50/p95/p99':>20}  alerts")
    for (name, hogs), r in results.items():
        if r is None:
            continue
        for traj, d in r["demo"].items():
            comp = f"{_f(d, 'pipeline_ms', 'p50')}/{_f(d, 'pipeline_ms', 'p95')}/{_f(d, 'pipeline_ms', 'p99')}"
            print(f"{traj:<10} {name:<13} {hogs:>4} {d['fps']:6.2f} {100 * d['tracking_fraction']:7.2f}% "
                  f"{_f(d, 'latency_ms', 'p95'):>7} {_f(d, 'pose_age_ms', 'p50'):>7} {_f(d, 'pose_age_ms', 'p95'):>7} "
                  f"{_f(d, 'detect_register_ms', 'p50', nd=2):>11} {comp:>20}  {','.join(d['alerts']) or '-'}")
            slow = d.get("slowest_5pct_stages_ms")
            if slow:
                print(f"{'':<10} {'':<13} {'':>4}   the slowest 5 % of frames, median ms: "
                      + ", ".join(f"{k} {v:.2f}" for k, v in slow.items()))
    print(f"(load {os.getloadavg()[0]:.2f} at the end)")
    ours = results.get(("ours", 0)) or {}
    dr = [st["detect_register"]["p50"] for c, st in ours.get("stages", {}).items() if c.startswith("720p")]
    br = ours.get("demo", {}).get("breathing", {})
    out = {"detect_register_ms_median": max(dr) if dr else None, "fps": br.get("fps"),
           "tracking_fraction": br.get("tracking_fraction"), "baseline": a.baseline,
           "runs": {f"{n} hogs={h}": r for (n, h), r in results.items()}}
    if a.average:
        avg = results.get((f"ours avg={a.average}", 0)) or {}
        dr = [st["detect_register"]["p50"] for c, st in avg.get("stages", {}).items() if c.startswith("720p")]
        out["detect_register_ms_median_average"] = max(dr) if dr else None
    print(json.dumps(out))


if __name__ == "__main__":
    main()
