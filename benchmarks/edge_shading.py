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

Per ray (:func:`ray_profile`): the residual against the true outline binned by how much the
background darkens towards the ball (near / far luma just beyond the blurred edge), and the
known-shape fit with and without the rays of a darkening background (the contact-shadow side):
the shadow's rays lie outside, but dropping them does not remove the centre error (the lit side
lies inside the true outline too).

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


def _ball_edge_points(img, centre, radius_px, shape):
    """``(ellipse, blur px, edge points px, usable)`` of the edge fit for one ball whose true ellipse centre is ``centre``
    (px), radius ``radius_px`` and outline ``shape`` (axis ratio, angle deg), with the blur measured
    on that ball; None when the ball is too close to the border."""
    ell = ((float(centre[0]), float(centre[1])), (2 * radius_px / shape[0], 2 * radius_px), float(shape[1]))
    blur = edge_fit.measure_edge_blur(img, [ell]) or edge_fit.BLUR_PROBE_PX
    got = edge_fit._edge_points(img, [ell], blur)[0]
    return None if got is None else (ell, blur, *got)


def harmonics(img, centre, radius_px, shape) -> tuple | None:
    """(first-harmonic amplitude px, its direction deg, second-harmonic amplitude px, rest RMS px) of
    the edge residuals of one ball round its true ellipse ``centre`` (px); None when the fit fails."""
    got = _ball_edge_points(img, centre, radius_px, shape)
    if got is None:
        return None
    ell, blur, pts, u = got
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


#: bins of the near / far background luma ratio of a ray (:func:`ray_profile`): < 1 = the
#: background darkens towards the ball (a contact shadow, ambient occlusion)
NF_BINS = (0.0, 0.5, 0.7, 0.8, 0.9, 0.95, 1.05, np.inf)
#: drop rays whose near / far ratio is below this (the shadow-ray variant of :func:`ray_profile`)
SHADOW_NF = 0.8
#: the far background sample lies this far (px) beyond the near one
FAR_PX = 3.0


def _luma_at(lin_y: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Linear luma (bilinear) at points (n, 2) px."""
    import cv2

    return cv2.remap(lin_y, pts[None, :, 0].astype(np.float32), pts[None, :, 1].astype(np.float32),
                     cv2.INTER_LINEAR)[0]


def ray_profile(img, centre, radius_px, shape) -> dict | None:
    """Per ray of one whole ball (rays from its true ellipse ``centre``, px, the frame's measured
    blur), as the edge fit sees it: ``res`` the edge's residual (px, + outside) against the TRUE
    outline, ``nf`` the background's linear luma just beyond the blurred edge over that
    :data:`FAR_PX` further out, ``limb`` the ball's luma just inside the edge over the median of
    its inner half, ``usable``; and the known-shape fits (centre error px against the true
    ellipse centre, cut) with all usable rays and without the rays of ``nf`` < :data:`SHADOW_NF`
    (the contact-shadow side). None when the ball is too close to the border."""
    got = _ball_edge_points(img, centre, radius_px, shape)
    if got is None:
        return None
    ell, blur, pts, u = got
    y = (edge_fit.LINEAR_LUT[img] @ np.array([0.114, 0.587, 0.299], np.float32)).astype(np.float32)
    c = np.asarray(centre, float)
    d = pts - c
    ud = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    rp = blur / (edge_fit.BLUR_PER_WIDTH * edge_fit.DISC_WIDTH_PER_RADIUS) + edge_fit.NEAR_BG_MARGIN_PX
    near, far = _luma_at(y, pts + rp * ud), _luma_at(y, pts + (rp + FAR_PX) * ud)
    inner = _luma_at(y, c + 0.5 * d)
    out = {"res": edge_fit._ellipse_residuals(pts, ell), "nf": near / np.maximum(far, 1e-6),
           "limb": _luma_at(y, pts - rp * ud) / max(float(np.median(inner)), 1e-6), "usable": u}
    for name, use in (("all", u), ("no_shadow", u & (out["nf"] >= SHADOW_NF))):
        fit = edge_fit._robust_ellipse(pts, use, shape) if use.sum() >= edge_fit.MIN_RAY_SHARE * len(u) else None
        out[name] = None if fit is None else (float(np.linalg.norm(np.array(fit[0][0]) - c)),
                                              bool(edge_fit._hidden_arc(pts, use, fit[0], shape, blur)))
    return out


def _ray_rows(profiles: list) -> dict:
    """Per :data:`NF_BINS` bin: usable rays, mean / median residual against the true outline (px);
    and per fit variant: balls fitted, refused as cut, mean centre error of all fitted (px)."""
    res = np.concatenate([p["res"][p["usable"]] for p in profiles]) if profiles else np.zeros(0)
    nf = np.concatenate([p["nf"][p["usable"]] for p in profiles]) if profiles else np.zeros(0)
    bins = {}
    for lo, hi in zip(NF_BINS[:-1], NF_BINS[1:]):
        m = (nf >= lo) & (nf < hi)
        bins[f"{lo:g}-{hi:g}"] = {"rays": int(m.sum()), "res_mean_px": float(res[m].mean()) if m.any() else float("nan"),
                                  "res_median_px": float(np.median(res[m])) if m.any() else float("nan")}
    fits = {}
    for name in ("all", "no_shadow"):
        got = [p[name] for p in profiles]
        ok = [g for g in got if g is not None]
        fits[name] = {"balls": len(got), "fitted": len(ok), "cut": int(sum(g[1] for g in ok)),
                      "err_mean_px": float(np.mean([g[0] for g in ok])) if ok else float("nan")}
    return {"nf_bins": bins, "fits": fits}


def pbr_rows(scenes, frames: int) -> dict:
    out = {}
    for cond, spec in CONDITIONS.items():
        cs = [s for s in scenes if s.spec.kind == spec["kind"]]
        if not cs:
            continue
        whole = found = 0
        errs, h1, h2, rest, spread = [], [], [], [], []
        why = collections.Counter()
        profiles = []
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
                    p = ray_profile(img, e, r, sh if sh is not None else (1.0, 0.0))
                    if p is not None:
                        profiles.append(p)
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
                     "h1_direction_agreement": float(np.mean(spread)) if spread else float("nan"),
                     "rays": _ray_rows(profiles)}
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
        print(f"per ray, residual vs the true outline (px, + outside) by near/far background luma ratio (usable rays); "
              f"known-shape fits with all rays / without rays of near/far < {SHADOW_NF}:")
        for cond, o in res["pbr"].items():
            print(f"{cond:<14} " + "  ".join(f"{k}: {v['res_mean_px']:+.2f} ({v['rays']})" for k, v in o["rays"]["nf_bins"].items()))
            print(f"{'':<14} " + "  ".join(f"{k}: {v['fitted']}/{v['balls']} fitted, {v['cut']} cut, err {v['err_mean_px']:.3f} px"
                                           for k, v in o["rays"]["fits"].items()))
        print("h1: first harmonic of the edge residuals round the true centre (a centre shift); agree: length of "
              "the mean unit vector of its direction over a frame's balls (1 = all alike)")
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
