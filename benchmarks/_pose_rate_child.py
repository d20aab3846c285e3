"""One tree's half of ``benchmarks/pose_rate.py`` (run with that tree's ``app`` on PYTHONPATH; uses
only APIs that the baseline commit has too). Prints one JSON line: per-stage times at 720p and
1080p, and the headless demo's figures (still, breathing) on the simulated clock."""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

STAGES = ("read", "hint", "average", "detect", "register", "screen", "gates", "motion", "other", "publish", "after")


def _pct(a):
    a = np.asarray(a, float) * 1000
    a = a[np.isfinite(a)]
    if a.size == 0:
        return None
    return {"p50": round(float(np.median(a)), 3), "p95": round(float(np.percentile(a, 95)), 3),
            "p99": round(float(np.percentile(a, 99)), 3)}


def stage_case(radius_px: float, hd: bool, n: int, head: str = "breathing", average: int = 0) -> dict:
    """Per stage (ms) of the app's pose tracker on ``n`` photo-like frames of a ``head``
    ("breathing" or "still"); ``average``: the tracker's ``average_still_frames`` (0: this
    tree's default config)."""
    from detect_budget import _rules, make_frames

    from monotracker.engine.config import SessionConfig
    from monotracker.engine.rigs.base import estimate_to_sample
    from monotracker.vision.detect_classical import ClassicalDetector
    from monotracker.vision.frames import Frame
    from monotracker.vision.pose_tracker import PoseTracker

    cam, frames = make_frames(radius_px, head, n, hd)
    every = int(getattr(SessionConfig(), "camera_motion_every", 0))   # as this tree's app builds it
    watch = None
    if every > 0:
        from monotracker.vision import camera_motion as cm

        watch = cm.CameraMotionMonitor(float(cam.camera.K[0, 0]), cm.MotionConfig(every_n_frames=every))
        if hasattr(cm, "DeferredMotionWatch"):   # as the app's rigs build it: a due check after the pose
            watch = cm.DeferredMotionWatch(watch)
    ph = cam.phantom
    extra = {}
    if average:
        from monotracker.vision.pose_tracker import TrackerConfig

        extra["config"] = TrackerConfig(average_still_frames=average)
    trk = PoseTracker(cam.fiducials_ct, cam.camera, detector=ClassicalDetector(_rules(radius_px, cam)),
                      radius_mm=ph.fiducial_radius_mm, target_ct=ph.sample_target_lps, camera_motion=watch, **extra)
    ids = list(range(len(cam.fiducials_ct)))
    rows, ok, errs = [], 0, []
    for i, (img, tr) in enumerate(frames):
        t0 = time.perf_counter()
        frame = Frame(np.array(img, copy=True), i / 30.0, i, tr)   # the driver's hand-over: a copy
        t1 = time.perf_counter()
        est = trk.process(frame)
        t2 = time.perf_counter()
        estimate_to_sample(est, ids)
        t3 = time.perf_counter()
        after = getattr(trk, "after_publish", None)
        if after is not None:
            after()           # the work after the pose is out (a due frame's motion check), as the rigs run it
        t4 = time.perf_counter()
        ok += bool(est.ok)
        for j in np.flatnonzero(tr.visible):
            if np.all(np.isfinite(est.image_points_px[j])):
                errs.append(float(np.linalg.norm(est.image_points_px[j] - tr.ellipse_centres_px[j])))
        if i == 0:
            continue     # a cold start in every pipeline
        s = dict(est.stages_s)
        known = sum(s.get(k, 0.0) for k in ("hint", "average", "detect", "register", "screen", "gates"))
        s.update({"read": t1 - t0, "publish": t3 - t2, "after": t4 - t3, "other": max(0.0, (t2 - t1) - known - s.get("motion", 0.0)),
                  "total": (t2 - t1) + (t3 - t2) + (t1 - t0), "detect_register": known})
        rows.append(s)
    out = {k: _pct([r.get(k, np.nan) for r in rows]) for k in STAGES + ("detect_register", "total")}
    out["trusted"] = ok / len(frames)
    out["centre_err_px"] = round(float(np.mean(errs)), 4) if errs else None
    return out


def demo(trajectory: str, seconds: float, home: Path, average: int = 0) -> dict:
    """The headless demo (simulated clock) with a listener for pose age and tracking after lock."""
    from monotracker.demo.run import DemoOptions, run_demo

    ticks, stages = [], []
    seen = {"sample": None, "trusted_capture": None}

    def on_tracking(s):
        def tick(t):
            rec = s.latest_pose()
            if rec is not None and rec.sample is not seen["sample"]:
                seen["sample"] = smp = rec.sample
                st = dict(getattr(smp.raw, "stages_s", None) or {})
                if smp.t_ready is not None:
                    st["pipeline"] = smp.t_ready - smp.t_capture - 0.030   # the sim clock's compute charge
                stages.append(st)
                if rec.trusted:
                    seen["trusted_capture"] = smp.t_capture
            st = s.robot_status()
            age = None if seen["trusted_capture"] is None else t - seen["trusted_capture"]
            ticks.append((t, st.state if st is not None else "disarmed", age))
        s.add_tick_listener(tick)

    over = {"average_still_frames": average} if average else {}
    r = run_demo(DemoOptions(seconds=seconds, trajectory=trajectory, home=home, config_overrides=over),
                 on_tracking=on_tracking)
    ages = [a for _, _, a in ticks if a is not None]
    dr = [sum(s.get(k, 0.0) for k in ("hint", "detect", "register", "screen", "gates")) for s in stages if "detect" in s]
    codes = sorted({a["code"] for a in r["alerts"]} - {"fiducial_unverified"})
    # what the slowest frames spend their time on: each stage's median (ms) over the frames whose
    # charged compute is at or above its 95th percentile (the frames behind the latency's p95)
    pipe = np.array([s.get("pipeline", np.nan) for s in stages], float)
    slow = [s for s, p in zip(stages, pipe) if np.isfinite(p) and p >= np.nanpercentile(pipe, 95)] if np.isfinite(pipe).any() else []
    at_p95 = {k: round(1000 * float(np.median([s.get(k, 0.0) for s in slow])), 2)
              for k in ("pipeline", "hint", "detect", "register", "screen", "gates", "motion")} if slow else None
    return {"fps": round(r["fps"], 2), "tracking_fraction": round(sum(st == "tracking" for _, st, _ in ticks) / max(1, len(ticks)), 4),
            "latency_ms": ({"mean": round(r["latency_ms"]["mean"], 1), "p95": round(r["latency_ms"]["p95"], 1)}
                           if r["latency_ms"] else None),
            "pose_age_ms": _pct(np.asarray(ages)), "detect_register_ms": _pct(dr),
            "pipeline_ms": _pct([s["pipeline"] for s in stages if "pipeline" in s]), "alerts": codes,
            "slowest_5pct_stages_ms": at_p95}


def main():
    import argparse

    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--cases", default="720:13,720:20,1080:20")
    ap.add_argument("--home", required=True)
    ap.add_argument("--head", default="breathing", choices=("breathing", "still"))
    ap.add_argument("--average", type=int, default=0)
    a = ap.parse_args()
    out = {"stages": {}, "demo": {}}
    for case in a.cases.split(","):
        res, r = case.split(":")
        hd = res == "1080"
        r_px = float(r) / (1.5 if hd else 1.0)      # make_frames' radius is at 720p
        out["stages"][f"{res}p {r}px"] = stage_case(r_px, hd, a.frames, a.head, a.average)
    for traj in ("still", "breathing"):
        home = Path(tempfile.mkdtemp(prefix="mt_pose_rate_demo_"))
        shutil.copy(Path(a.home) / "plan.json", home / "plan.json")
        out["demo"][traj] = demo(traj, a.seconds, home, a.average)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
