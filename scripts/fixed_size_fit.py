"""Prototype (issue 28 item 2): the centre of a shaded ball fitted with its image SIZE known
(from geometry: the kit's radius and the ball's depth), through the rays one can trust.

On the committed tuning crops (``tests/data/pbr/tuning``; truth from the scene) per whole ball:
the product's edge points (rays from a coarse ellipse ~0.5 px off the truth, the frame's
measured blur), then centre-only fits of the outline of the TRUE size and shape through
several ray selections; the product's own known-shape fit (centre and size free, the
contact-shadow rays left out) is the baseline. Centre error against the true ellipse centre (px).

Usage: PYTHONPATH=app python scripts/fixed_size_fit.py [--frames N] [--size-err PCT]
"""

from __future__ import annotations

import argparse
import json
import sys

import cv2
import numpy as np

from monotracker.sim.pbr.frameset import CONDITIONS, camera_frames, committed_root, list_scenes
from monotracker.vision import edge_fit
from monotracker.vision.sphere_outline import expected_shapes


def fit_centre(pts, use, axes, ang, c0, w=None, iters=5):
    """Centre (2,) of the ellipse of fixed semi-axes ``axes`` (a along ``ang`` deg, b) through
    ``pts[use]``: Gauss-Newton on the stretched-circle distance, from ``c0``."""
    ca, sa = np.cos(np.radians(ang)), np.sin(np.radians(ang))
    a, b = axes
    ratio = b / a
    p = pts[use]
    ww = np.ones(len(p)) if w is None else w[use]
    c = np.array(c0, float)
    for _ in range(iters):
        d = p - c
        u = (d[:, 0] * ca + d[:, 1] * sa) * ratio
        v = -d[:, 0] * sa + d[:, 1] * ca
        rho = np.maximum(np.hypot(u, v), 1e-9)
        r = rho - b
        # d rho / d c (in image coordinates)
        du_dc = -np.array([ca, sa]) * ratio
        dv_dc = -np.array([-sa, ca])
        J = (u[:, None] * du_dc[None, :] + v[:, None] * dv_dc[None, :]) / rho[:, None]
        A = J.T @ (J * ww[:, None])
        if np.linalg.cond(A) > 1e8:
            return None
        c = c - np.linalg.solve(A, J.T @ (ww * r))
    return c


def signed_res(pts, c, axes, ang):
    return edge_fit._ellipse_residuals(pts, ((c[0], c[1]), (2 * axes[0], 2 * axes[1]), ang))


def variants(pts, usable, axes, ang, c0, feats):
    """{name: centre or None} for the ray selections tried."""
    out = {}
    n = len(pts)
    enough = lambda m: m.sum() >= max(0.3 * n, 6)       # noqa: E731
    c_all = fit_centre(pts, usable, axes, ang, c0)
    out["fix_all"] = c_all
    # robust symmetric (3 MAD), fixed size
    c = c_all
    keep = usable.copy()
    for _ in range(3):
        if c is None:
            break
        r = signed_res(pts, c, axes, ang)
        med = np.median(r[keep])
        sc = max(1.4826 * np.median(np.abs(r[keep] - med)), 0.08)
        keep = usable & (np.abs(r - med) < 3 * sc)
        c = fit_centre(pts, keep, axes, ang, c) if enough(keep) else None
    out["fix_robust"] = c
    # one-sided: rays more than t outside the fixed-size fit dropped, iterated
    for t in (0.2, 0.35, 0.5):
        c = c_all
        for _ in range(6):
            if c is None:
                break
            r = signed_res(pts, c, axes, ang)
            keep = usable & (r < t)
            c = fit_centre(pts, keep, axes, ang, c) if enough(keep) else None
        out[f"fix_out<{t}"] = c
    # contact-shadow rays (background darkening towards the ball) left out
    for nfmin in (0.8, 0.9):
        keep = usable & (feats["nf"] >= nfmin)
        out[f"fix_nf>={nfmin}"] = fit_centre(pts, keep, axes, ang, c0) if enough(keep) else None
    # the lit half: ball limb luma relative to the ball's median inner luma
    for q in (0.5,):
        lim = feats["inner"]
        keep = usable & (lim >= np.quantile(lim[usable], q))
        out[f"fix_lit{q}"] = fit_centre(pts, keep, axes, ang, c0) if enough(keep) else None
    # contrast: ball limb against the near background (colour distance, relative)
    for q in (0.5,):
        con = feats["contrast"]
        keep = usable & (con >= np.quantile(con[usable], q))
        out[f"fix_con{q}"] = fit_centre(pts, keep, axes, ang, c0) if enough(keep) else None
    return out


def run(frames, conds, size_err):
    scenes = list_scenes(committed_root() / "tuning")
    rows = {}
    rng = np.random.default_rng(3)
    for cond in conds:
        spec = CONDITIONS[cond]
        E = {}
        for s in scenes:
            if s.spec.kind != spec["kind"]:
                continue
            cam, tr = s.camera_model(), s.truth
            whole = np.flatnonzero(tr.whole)
            for img in camera_frames(s, cond, frames):
                ells, shapes, truths = [], [], []
                for j in whole:
                    e, r = tr.ellipse_centres_px[j], float(tr.radius_px[j])
                    sh = expected_shapes(cam, [e], [r])[0] or (1.0, 0.0)
                    off = rng.normal(0, 0.4, 2)
                    ells.append(((float(e[0] + off[0]), float(e[1] + off[1])), (2 * r / sh[0] + 0.8, 2 * r + 0.8),
                                 float(sh[1])))
                    shapes.append(sh)
                    truths.append((e, r, sh))
                blur = edge_fit.measure_edge_blur(img, ells) or edge_fit.BLUR_PROBE_PX
                prod = edge_fit.fit_ball_edges(img, ells, blur, shapes)
                pts_all = edge_fit._edge_points(img, ells, blur)
                y = (edge_fit.LINEAR_LUT[img] @ np.array([0.114, 0.587, 0.299], np.float32)).astype(np.float32)
                rp = blur / (edge_fit.BLUR_PER_WIDTH * edge_fit.DISC_WIDTH_PER_RADIUS) + edge_fit.NEAR_BG_MARGIN_PX
                lin = edge_fit.LINEAR_LUT[img]

                def at(im, p):
                    return cv2.remap(im, p[None, :, 0].astype(np.float32), p[None, :, 1].astype(np.float32),
                                     cv2.INTER_LINEAR)[0]

                for ell, (e, r, sh), got, pf in zip(ells, truths, pts_all, prod):
                    E.setdefault("product", []).append(np.linalg.norm(pf.centre_px - e) if pf.ok else np.nan)
                    if got is None:
                        continue
                    pts, usable = got
                    c = np.array(ell[0])
                    d = pts - c
                    ud = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
                    near, far = at(y, pts + rp * ud), at(y, pts + (rp + 3.0) * ud)
                    inner = at(y, pts - rp * ud)
                    cin, cnear = at(lin, pts - rp * ud), at(lin, pts + rp * ud)
                    feats = {"nf": near / np.maximum(far, 1e-6), "inner": inner,
                             "contrast": np.linalg.norm(cin - cnear, axis=-1) / np.maximum(
                                 np.linalg.norm(cnear, axis=-1), 1e-6)}
                    f = 1.0 + size_err / 100.0
                    axes = (f * r / sh[0], f * r)
                    for name, cc in variants(pts, usable, axes, sh[1], c, feats).items():
                        E.setdefault(name, []).append(np.nan if cc is None else np.linalg.norm(cc - e))
        rows[cond] = {k: {"balls": len(v), "fitted": int(np.sum(np.isfinite(v))), "mean": float(np.nanmean(v)),
                          "p90": float(np.nanpercentile(v, 90))} for k, v in E.items()}
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=1)
    ap.add_argument("--size-err", type=float, default=0.0, help="size error of the fixed outline, percent")
    ap.add_argument("--conditions", default="clean,OR,degraded,clutter")
    a = ap.parse_args(argv)
    rows = run(a.frames, a.conditions.split(","), a.size_err)
    for cond, out in rows.items():
        print(f"== {cond}")
        for name, o in out.items():
            print(f"{name:<16} {o['fitted']:>4}/{o['balls']:<4} mean {o['mean']:.3f} p90 {o['p90']:.3f}")
    print(json.dumps(rows))


if __name__ == "__main__":
    sys.exit(main())
