"""Per-frame budget of the pose pipeline's vision stages (issue 29 item 1): the balls' predicted
ellipses (hint), detection, registration, screening and gates, per stage, per frame, on one core.

Target: hint + detect + register + screen + gates <= 10 ms median and <= 16 ms p99 per 1280x720
frame with 9 balls of 8-20 px, <= 20 ms at 1920x1080; centres as accurate as today's detector.

Frames: our simulator (``monotracker.sim``), photo-like optics (gloss, 1.5 px defocus, Bayer,
raw noise, JPEG 85), 9 balls, a breathing head (``breathing``) and a head moving in all six
degrees of freedom (``mixed``), 30 fps; ball radius set by the camera distance (8, 13, 20 px at
1280x720 f = 1100 px; 1920x1080 is the same lens at 1.5 x the resolution). Rendering is not timed.

Pipelines, each through :class:`~monotracker.vision.pose_tracker.PoseTracker` (fresh per run):
* ``today``: the detector of commit :data:`BASELINE_COMMIT` (before this work), loaded from git
  into a private package, so the baseline is measured in the same run on the same frames (a
  full-frame search and an edge-blur probe every frame, ball by ball fits);
* ``cold``: this checkout's detector with no hint (every frame a cold full-frame search);
* ``tracked``: this checkout as the product runs it: windows around the predicted balls, the
  whole frame every ``full_search_every`` frames, the edge blur carried over between frames.

Columns: total = hint + detect + register + screen + gates (wall ms, median and p99 over the
frames, the first frame excluded: it is a cold search in every pipeline), then each stage's
median (detect's own stages: mask, contours, shape, outline, blur, edge_fit), trusted % of the
frames, the mean / p95 centre error (px) of the accepted whole balls against the simulator's
exact ellipse centres, and recall of whole balls.

Usage: ``cpu --quiet .venv/bin/python benchmarks/detect_budget.py [--quick] [--json]``; the
last line is a JSON object (``detect_register_ms_median`` / ``_p99`` of the tracked pipeline at
720p (the worst ball size), per-case figures, and the baseline's).
:func:`run_case` is the detect stage's timing for other benchmarks (``pose_rate.py``).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from monotracker.sim.camera_sim import SimulatedCamera
from monotracker.sim.trajectories import make_trajectory
from monotracker.vision.camera_model import CameraModel, default_camera
from monotracker.vision.detect_classical import ClassicalDetector
from monotracker.vision.detection import BlobRules
from monotracker.vision.frames import Frame
from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig

#: the commit whose detector is the same-run baseline (the last one before issue 29's detector work)
BASELINE_COMMIT = "83424c7"
_BASELINE_FILES = ("ball_colour", "detection", "edge_fit", "sphere_outline", "detect_classical")
REPO = Path(__file__).resolve().parents[1]


def baseline_detector_class():
    """``ClassicalDetector`` of :data:`BASELINE_COMMIT`, imported from ``git show`` into a
    private package; None (with the reason printed) when this is not a git checkout."""
    try:
        src = {n: subprocess.run(["git", "-C", str(REPO), "show", f"{BASELINE_COMMIT}:app/monotracker/vision/{n}.py"],
                                 check=True, capture_output=True, text=True).stdout for n in _BASELINE_FILES}
    except (OSError, subprocess.CalledProcessError) as exc:
        print(f"(baseline {BASELINE_COMMIT} not available: {exc}; needs the git checkout)")
        return None
    root = Path(tempfile.mkdtemp(prefix="mt_baseline_"))
    pkg = root / f"vision_{BASELINE_COMMIT}"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    for n, text in src.items():
        (pkg / f"{n}.py").write_text(text)
    sys.path.insert(0, str(root))
    return importlib.import_module(f"vision_{BASELINE_COMMIT}.detect_classical").ClassicalDetector


def camera_1080p() -> CameraModel:
    """The simulator's lens at 1920x1080 (intrinsics x 1.5, same distortion)."""
    c = default_camera()
    K = c.K.copy()
    K[:2] *= 1.5
    return CameraModel(K, c.dist.copy(), (1920, 1080))


def make_frames(radius_px: float, motion: str, n: int, hd: bool = False, seed: int = 3):
    """``n`` frames (image, truth) at 30 fps of the simulator with photo-like optics, balls of
    ``radius_px`` (px at 1280x720; x 1.5 at 1920x1080 with ``hd``), and the camera."""
    cam_model = camera_1080p() if hd else None
    dist = 1100.0 * 4.0 / radius_px
    cam = SimulatedCamera(camera=cam_model, seed=seed, optics="photo", distance_mm=dist,
                          trajectory=make_trajectory(motion, seed=seed))
    return cam, [cam.render(i / 30.0) for i in range(n)]


def run_case(cam, frames, detector, config: TrackerConfig | None = None) -> dict:
    """Run ``frames`` ((image, truth) pairs) through a fresh :class:`PoseTracker` with
    ``detector``; per frame (the first, a cold start, excluded from the timing statistics)
    the stage times (s, ``PoseEstimate.stages_s``) and the accepted centres' errors against
    the truth's ellipse centres. Returns {"stages": {stage: array s}, "total": array s,
    "trusted": share, "err": array px, "recall": share}."""
    ph = cam.phantom
    trk = PoseTracker(cam.fiducials_ct, cam.camera, detector=detector, radius_mm=ph.fiducial_radius_mm,
                      target_ct=ph.sample_target_lps, config=config)
    stages: dict = {}
    totals, errs, found, whole, ok = [], [], 0, 0, 0
    for i, (img, tr) in enumerate(frames):
        est = trk.process(Frame(img, i / 30.0, i, tr))
        ok += est.ok
        pts = est.image_points_px
        for j in np.flatnonzero(tr.visible):
            whole += 1
            if np.all(np.isfinite(pts[j])):
                found += 1
                errs.append(float(np.linalg.norm(pts[j] - tr.ellipse_centres_px[j])))
        if i == 0:
            continue
        s = est.stages_s
        for k, v in s.items():
            stages.setdefault(k, []).append(v)
        totals.append(sum(s.get(k, 0.0) for k in ("hint", "detect", "register", "screen", "gates")))
    return {"stages": {k: np.array(v) for k, v in stages.items()}, "total": np.array(totals),
            "trusted": ok / len(frames), "err": np.array(errs), "recall": found / max(whole, 1)}


def _rules(radius_px: float, cam) -> BlobRules:
    dist = 1100.0 * 4.0 / radius_px
    return BlobRules(radius_mm=4.0, focal_px=float(cam.camera.K[0, 0]), min_distance_mm=min(250.0, 0.8 * dist),
                     max_distance_mm=max(1000.0, 1.2 * dist))


STAGE_COLS = ("hint", "detect.mask", "detect.contours", "detect.shape", "detect.outline", "detect.blur",
              "detect.edge_fit", "register", "screen", "gates")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="60 frames per case, fewer cases (default 240)")
    ap.add_argument("--json", action="store_true", help="(the last line is JSON either way)")
    a = ap.parse_args(argv)
    n = 60 if a.quick else 240
    cases = [(8, "breathing", False), (13, "breathing", False), (20, "breathing", False), (13, "mixed", False),
             (13, "breathing", True), (20, "breathing", True)]
    if a.quick:
        cases = [(8, "breathing", False), (20, "breathing", False), (13, "mixed", False), (20, "breathing", True)]
    print(f"detect budget: {n} frames per case at 30 fps, photo-like optics, 9 balls; {os.cpu_count()} CPUs, "
          f"load {os.getloadavg()[0]:.2f} at the start (run it under `cpu --quiet`)")
    Baseline = baseline_detector_class()
    print(f"\n{'case':<22} {'pipeline':<8} {'total ms':>8} {'p99':>6} " + " ".join(f"{c.split('.')[-1][:7]:>7}"
                                                                            for c in STAGE_COLS)
          + f" {'trusted':>7} {'err px':>6} {'p95':>5} {'recall':>6}")
    summary: dict = {}
    for r_px, motion, hd in cases:
        cam, frames = make_frames(r_px, motion, n, hd)
        label = f"{'1080p' if hd else '720p'} r{r_px * (1.5 if hd else 1):.0f}px {motion}"
        rules = _rules(r_px, cam)
        pipes = []
        if Baseline is not None:
            pipes.append(("today", Baseline(replace(rules)), None))
        pipes.append(("cold", ClassicalDetector(replace(rules)), TrackerConfig(hint_max_age_frames=0)))
        pipes.append(("tracked", ClassicalDetector(replace(rules)), None))
        for name, det, cfg in pipes:
            out = run_case(cam, frames, det, cfg)
            tot = 1000 * out["total"]
            st = out["stages"]
            cols = " ".join(f"{1000 * np.median(st[c]) if c in st else 0.0:7.2f}" for c in STAGE_COLS)
            e = out["err"] if len(out["err"]) else np.array([np.nan])
            print(f"{label:<22} {name:<8} {np.median(tot):8.2f} {np.percentile(tot, 99):6.2f} {cols} "
                  f"{100 * out['trusted']:6.1f}% {np.mean(e):6.3f} {np.percentile(e, 95):5.3f} {out['recall']:6.3f}")
            summary.setdefault(label, {})[name] = {"ms_median": round(float(np.median(tot)), 2),
                                                   "ms_p99": round(float(np.percentile(tot, 99)), 2),
                                                   "err_px_mean": round(float(np.mean(e)), 4),
                                                   "trusted": round(out["trusted"], 3),
                                                   "recall": round(out["recall"], 3)}
    print(f"(load {os.getloadavg()[0]:.2f} at the end)")
    t720 = [v["tracked"] for k, v in summary.items() if k.startswith("720p")]
    t1080 = [v["tracked"] for k, v in summary.items() if k.startswith("1080p")]
    result = {"detect_register_ms_median": max(v["ms_median"] for v in t720),
              "detect_register_ms_p99": max(v["ms_p99"] for v in t720),
              "detect_register_ms_median_1080p": max((v["ms_median"] for v in t1080), default=None),
              "detect_register_ms_p99_1080p": max((v["ms_p99"] for v in t1080), default=None),
              "baseline_commit": BASELINE_COMMIT, "frames": n, "cases": summary}
    print(json.dumps(result))


if __name__ == "__main__":
    t0 = time.time()
    main()
    print(f"(total {time.time() - t0:.0f} s)", file=sys.stderr)
