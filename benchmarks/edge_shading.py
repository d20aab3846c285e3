"""Why shaded balls are refused or off-centre (issue 28 item 2): the edge fit's edges against the
exact outline, on physically rendered frames and on our renders.

Per condition: whole-ball recall and centre error of the edge detector (with the camera's
outlines, as the pose tracker runs it) and why the whole balls it missed were refused; then, per
whole ball, the edge fit's edge points (rays from the true ellipse centre, the frame's measured
blur) against the true outline: their residuals expanded in harmonics round the true centre. The
first harmonic is a centre shift (px): on the Mitsuba frames it points the same way for every ball
of a scene (towards the contact shadow), i.e. a common bias no residual shows. Reference rows: the
independent single-ball renders (``tests/vision/independent_render.py``: sharp raw, 1.5 px defocus
+ JPEG 85), which show none of it.

Frames: the committed tuning crops (``tests/data/pbr/tuning``; no Mitsuba needed) unless
``--root DIR`` names a folder of rendered scenes (the tuning split; never the held-out one).

Usage: PYTHONPATH=app python benchmarks/edge_shading.py [--root DIR] [--frames N] [--balls N] [--json]
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

import numpy as np

from monotracker.sim.pbr.frameset import CONDITIONS, camera_frames, committed_root, list_scenes
from monotracker.sim.pbr.truth import sphere_centre_px
from monotracker.vision import edge_fit
from monotracker.vision.detect_classical import ClassicalDetector
from monotracker.vision.detection import BlobRules
from monotracker.vision.sphere_outline import expected_shapes

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "vision"))


def harmonics(img, centre, radius_px, shape) -> tuple | None:
    """(first-harmonic amplitude px, its direction deg, second-harmonic amplitude px, rest RMS px) of
    the edge residuals of one ball round its true ellipse ``centre`` (px); None when the fit fails."""
    ell = ((float(centre[0]), float(centre[1])), (2 * radius_px / shape[0], 2 * radius_px), float(shape[1]))
    blur = edge_fit.measure_edge_blur(img, [ell]) or edge_fit.BLUR_PROBE_PX
    got = edge_fit._edge_points(img, [ell], blur)[0]
    if got is None:
        return None
    pts, u = got
    fit = edge_fit._robust_ellipse(pts, u, shape)
    if fit is None:
        return None
    (_c, (d1, d2), ang) = fit[0]
    res = edge_fit._ellipse_residuals(pts, ((float(centre[0]), float(centre[1])), (d1, d2), ang))[u]
    phi = np.arctan2(pts[u, 1] - centre[1], pts[u, 0] - centre[0])
    A = np.column_stack([np.ones_like(phi), np.cos(phi), np.sin(phi), np.cos(2 * phi), np.sin(2 * phi)])
    co = np.linalg.lstsq(A, res, rcond=None)[0]
    return (float(np.hypot(co[1], co[2])), float(np.degrees(np.arctan2(co[2], co[1]))),
            float(np.hypot(co[3], co[4])), float(np.std(res - A @ co)))


def pbr_rows(scenes, frames: int) -> dict:
    out = {}
    for cond, spec in CONDITIONS.items():
        cs = [s for s in scenes if s.spec.kind == spec["kind"]]
        if not cs:
            continue
        whole = found = 0
        errs, h1, h2, rest, spread = [], [], [], [], []
        why = collections.Counter()
        for s in cs:
            cam, tr = s.camera_model(), s.truth
            det = ClassicalDetector(BlobRules(radius_mm=tr.radius_mm, focal_px=float(cam.K[0, 0]), camera=cam))
            for img in camera_frames(s, cond, frames):
                d = det.detect(img)
                dirs = []
                for j in np.flatnonzero(tr.whole):
                    whole += 1
                    e, r = tr.ellipse_centres_px[j], float(tr.radius_px[j])
                    tol = max(2.0, 0.5 * r)
                    acc = [f for f in d.fiducials if np.linalg.norm(f.centre_px - e) < tol]
                    if acc:
                        found += 1
                        sp = sphere_centre_px(acc[0].centre_px[None], tr.fiducials_cam[j, 2:3], tr.radius_mm, cam.K,
                                              cam.dist)[0]
                        errs.append(float(np.linalg.norm(sp - tr.projected_centres_px[j])))
                    else:
                        rj = [f for f in d.rejected if np.linalg.norm(f.centre_px - e) < max(3.0, 0.7 * r)]
                        reason = rj[0].reason.split(" (")[0] if rj else "no candidate"
                        why["score: " + reason.split(": ", 1)[1] if reason.startswith("score") else reason] += 1
                    sh = expected_shapes(cam, [e], [r])[0]
                    h = harmonics(img, e, r, sh if sh is not None else (1.0, 0.0))
                    if h is not None:
                        h1.append(h[0])
                        h2.append(h[2])
                        rest.append(h[3])
                        dirs.append(np.radians(h[1]))
                if len(dirs) >= 3:      # how alike the shift's direction is across the scene's balls
                    spread.append(float(np.hypot(np.mean(np.cos(dirs)), np.mean(np.sin(dirs)))))
        out[cond] = {"whole": whole, "recall": found / whole if whole else float("nan"),
                     "centre_err_mean_px": float(np.mean(errs)) if errs else float("nan"),
                     "missed_by": dict(why.most_common()),
                     "h1_px": float(np.mean(h1)), "h2_px": float(np.mean(h2)), "rest_px": float(np.mean(rest)),
                     "h1_direction_agreement": float(np.mean(spread)) if spread else float("nan")}
    return out


def independent_rows(n: int, seed: int = 7) -> dict:
    from independent_render import Imaging, render_ball

    rng = np.random.default_rng(seed)
    out = {}
    for name, im in (("ind-sharp", Imaging(defocus_px=0.0, gauss_px=0.4, jpeg_quality=0)),
                     ("ind-blur-jpeg", Imaging(defocus_px=1.5, gauss_px=0.5, jpeg_quality=85))):
        h1, h2, rest = [], [], []
        for k in range(n):
            r = float(rng.uniform(7, 12))
            sh = (float(rng.uniform(0.85, 1.0)), float(rng.uniform(0, np.pi)))
            img, c = render_ball(rng, r, im, split=bool(k % 2), shape=sh)
            h = harmonics(img, c, r * sh[0], (sh[0], float(np.degrees(sh[1]))))
            if h is not None:
                h1.append(h[0])
                h2.append(h[2])
                rest.append(h[3])
        out[name] = {"balls": len(h1), "h1_px": float(np.mean(h1)), "h2_px": float(np.mean(h2)),
                     "rest_px": float(np.mean(rest))}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=None, help="folder of rendered tuning scenes")
    ap.add_argument("--frames", type=int, default=1)
    ap.add_argument("--balls", type=int, default=60, help="independent single-ball renders per optics")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    folder = a.root or committed_root() / "tuning"
    if "held_out" in str(folder):
        print("error: the held-out set is only ever scored (benchmarks/camera_pbr.py --held-out)", file=sys.stderr)
        return 2
    scenes = list_scenes(folder) if Path(folder).is_dir() else []
    if not scenes:
        print(f"error: no rendered scenes in {folder}", file=sys.stderr)
        return 2
    res = {"folder": str(folder), "frames": a.frames, "pbr": pbr_rows(scenes, a.frames),
           "independent": independent_rows(a.balls)}
    if not a.json:
        print(f"edge fit vs the exact outline: {folder} ({len(scenes)} scenes, {a.frames} frame(s) each)")
        print(f"{'frames':<14} {'whole':>5} {'recall':>6} {'err px':>6} {'h1 px':>6} {'agree':>5} {'h2 px':>6} "
              f"{'rest px':>7}  missed by")
        for cond, o in res["pbr"].items():
            print(f"{cond:<14} {o['whole']:>5} {o['recall']:>6.2f} {o['centre_err_mean_px']:>6.3f} {o['h1_px']:>6.2f} "
                  f"{o['h1_direction_agreement']:>5.2f} {o['h2_px']:>6.2f} {o['rest_px']:>7.2f}  "
                  + ", ".join(f"{v} {k}" for k, v in list(o["missed_by"].items())[:3]))
        for name, o in res["independent"].items():
            print(f"{name:<14} {o['balls']:>5} {'':>6} {'':>6} {o['h1_px']:>6.2f} {'':>5} {o['h2_px']:>6.2f} "
                  f"{o['rest_px']:>7.2f}")
        print("h1: first harmonic of the edge residuals round the true centre (a centre shift); agree: length of "
              "the mean unit vector of its direction over a frame's balls (1 = all alike)")
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
