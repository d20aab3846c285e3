"""Measurement (issue 28 item 2): can a shaded ball's centre be fitted from the rays one trusts once
its image SIZE is known (from geometry: the kit's radius and the ball's depth from the pose)?

On the committed tuning crops (``tests/data/pbr/tuning``, the Mitsuba coverage image beside each;
truth from the scene), per whole ball: the product's edge points (rays from a coarse ellipse
~0.5 px off the truth, the frame's measured blur), then centre-only fits of the outline of the
TRUE shape and size (times ``1 + size error``) through several ray selections. Baseline: the
product's own known-shape fit (centre and size free, contact-shadow rays left out, the cut test),
on the same edge points. Centre error (px) against the true ellipse centre: over the balls each
variant fits, and over the balls the product accepts (the same balls for every row).

Rows: ``fix_all`` every usable ray; ``fix_robust`` rays within 3 MAD of the fixed-size fit;
``fix_out<t`` rays more than ``t`` px outside the fixed-size outline left out (iterated; the
shading errs outwards); ``fix_L1`` least absolute residuals; ``fix_nf>=0.9`` the contact-shadow
rays (background darker towards the ball) left out; ``lit`` the half of the rays facing the
lamp, which is told by the ball's own interior luma (its first harmonic round the ball, at 0.6 of
the radius), with the size fixed (``lit_fix``) or free (``lit_free``, the known-shape fit);
``lit_L1`` the rays up to ~107 deg from the lamp (cos > -0.3), size fixed, least absolute residuals;
``oracle_lit`` the half facing away from the truth's own error (the first harmonic of the rays'
errors against the coverage image: the best split any per-ball lit/dark rule can make),
``oracle_good`` the rays within 0.15 px of the true outline (where a ball has >= 6).

Per ray (usable rays): the edge's error against the true outline (px, + outside), its mean,
RMS, and its mean on the third of the rays facing the lamp and on the third facing away; and how
much of it a linear model of what the image shows round the ray predicts (:func:`regression`).

``--drawn``: the same fits on the drawn tinted ball of ``tests/vision/test_edge_fit_shadow.py``.

Usage: PYTHONPATH=app python scripts/fixed_size_fit.py [--frames N] [--size-err PCT ...] [--drawn] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from monotracker.sim.pbr.frameset import CONDITIONS, camera_frames, committed_root, list_scenes
from monotracker.vision import edge_fit
from monotracker.vision.sphere_outline import expected_shapes

sys.path.insert(0, str(Path(__file__).resolve().parent))
from edge_locators import cov_crossing, profiles

_Y = np.array([0.114, 0.587, 0.299], np.float32)


def fit_centre(pts, use, axes, ang, c0, w=None, iters=5):
    """Centre (2,) px of the ellipse of FIXED semi-axes ``axes`` (px; the first along ``ang`` deg)
    through ``pts[use]`` ((n, 2) px), optional weights ``w`` (n,): Gauss-Newton on the distance in
    the space where the ellipse is a circle, from ``c0``. None when the rays do not fix it."""
    if use.sum() < 6:
        return None
    ca, sa = np.cos(np.radians(ang)), np.sin(np.radians(ang))
    ratio = axes[1] / axes[0]
    p = pts[use]
    ww = np.ones(len(p)) if w is None else w[use]
    c = np.array(c0, float)
    du_dc = -np.array([ca, sa]) * ratio
    dv_dc = -np.array([-sa, ca])
    for _ in range(iters):
        d = p - c
        u = (d[:, 0] * ca + d[:, 1] * sa) * ratio
        v = -d[:, 0] * sa + d[:, 1] * ca
        rho = np.maximum(np.hypot(u, v), 1e-9)
        J = (u[:, None] * du_dc[None, :] + v[:, None] * dv_dc[None, :]) / rho[:, None]
        A = J.T @ (J * ww[:, None])
        if np.linalg.cond(A) > 1e8:
            return None
        c = c - np.linalg.solve(A, J.T @ (ww * (rho - axes[1])))
    return c


def signed_res(pts, c, axes, ang):
    """Signed distance (px, + outside) of points from the ellipse of centre ``c``, semi-axes ``axes``."""
    return edge_fit._ellipse_residuals(pts, ((c[0], c[1]), (2 * axes[0], 2 * axes[1]), ang))


def _harmonic_dir(phi, v):
    """Direction (rad) of the first harmonic of ``v`` round the ball (ray angles ``phi``)."""
    A = np.column_stack([np.ones_like(phi), np.cos(phi), np.sin(phi)])
    co = np.linalg.lstsq(A, v, rcond=None)[0]
    return float(np.arctan2(co[2], co[1]))


def _l1_centre(pts, use, axes, ang, c0):
    """:func:`fit_centre` with least absolute residuals (reweighted least squares)."""
    c = fit_centre(pts, use, axes, ang, c0)
    for _ in range(8):
        if c is None:
            break
        c = fit_centre(pts, use, axes, ang, c, w=1.0 / np.maximum(np.abs(signed_res(pts, c, axes, ang)), 0.05), iters=2)
    return c


def variants(pts, usable, axes, ang, shape, c0, phi, lit_dir, true_err) -> dict:
    """{name: centre (2,) px or None} for the ray selections (module docstring)."""
    out = {}
    c_all = fit_centre(pts, usable, axes, ang, c0)
    out["fix_all"] = c_all
    c, keep = c_all, usable.copy()
    for _ in range(3):
        if c is None:
            break
        r = signed_res(pts, c, axes, ang)
        med = np.median(r[keep])
        sc = max(1.4826 * np.median(np.abs(r[keep] - med)), 0.08)
        keep = usable & (np.abs(r - med) < 3 * sc)
        c = fit_centre(pts, keep, axes, ang, c)
    out["fix_robust"] = c
    for t in (0.35, 0.5):
        c = c_all
        for _ in range(6):
            if c is None:
                break
            c = fit_centre(pts, usable & (signed_res(pts, c, axes, ang) < t), axes, ang, c)
        out[f"fix_out<{t}"] = c
    out["fix_L1"] = _l1_centre(pts, usable, axes, ang, c0)
    out["fix_nf>=0.9"] = None
    lit = usable & (np.cos(phi - lit_dir) > 0.0)
    out["lit_fix"] = fit_centre(pts, lit, axes, ang, c0)
    fr = edge_fit._robust_ellipse(pts, lit, shape, 0.2) if lit.sum() >= 6 else None
    out["lit_free"] = None if fr is None else np.array(fr[0][0])
    out["lit_L1"] = _l1_centre(pts, usable & (np.cos(phi - lit_dir) > -0.3), axes, ang, c0)
    if true_err is not None:
        ok = usable & np.isfinite(true_err)
        dark = _harmonic_dir(phi[ok], true_err[ok])
        out["oracle_lit"] = fit_centre(pts, ok & (np.cos(phi - dark) < 0.0), axes, ang, c0)
        out["oracle_good"] = fit_centre(pts, ok & (np.abs(true_err) < 0.15), axes, ang, c0)
    return out


def run(frames: int, conds: list, size_errs: list) -> dict:
    scenes = list_scenes(committed_root() / "tuning")
    rows = {}
    per_ball = []       # for the per-ray regression (:func:`regression`)
    for cond in conds:
        rng = np.random.default_rng(3)
        E = {se: {} for se in size_errs}
        rays = {"err": [], "lit": [], "dark": []}
        ok_prod = []
        for s in scenes:
            if s.spec.kind != CONDITIONS[cond]["kind"]:
                continue
            cam, tr = s.camera_model(), s.truth
            for img in camera_frames(s, cond, frames):
                ells, truths = [], []
                for j in np.flatnonzero(tr.whole):
                    e, r = tr.ellipse_centres_px[j], float(tr.radius_px[j])
                    sh = expected_shapes(cam, [e], [r])[0] or (1.0, 0.0)
                    off = rng.normal(0, 0.4, 2)
                    ells.append(((float(e[0] + off[0]), float(e[1] + off[1])), (2 * r / sh[0] + 0.8, 2 * r + 0.8),
                                 float(sh[1])))
                    truths.append((e, r, sh))
                blur = edge_fit.measure_edge_blur(img, ells) or edge_fit.BLUR_PROBE_PX
                prod = edge_fit.fit_ball_edges(img, ells, blur, [t[2] for t in truths])
                pts_all = edge_fit._edge_points(img, ells, blur)
                ylin = (edge_fit.LINEAR_LUT[img] @ _Y).astype(np.float32)
                for ell, (e, r, sh), got, pf in zip(ells, truths, pts_all, prod):
                    if got is None:
                        continue
                    pts, usable = got
                    c = np.array(ell[0])
                    d = pts - c
                    rr = np.linalg.norm(d, axis=1)
                    phi = np.arctan2(d[:, 1], d[:, 0])
                    # the lamp's side: the first harmonic of the ball's interior luma at 0.6 r
                    pr = profiles(img, ell, blur)
                    sp = pr["s0"][:, None] + np.arange(pr["rgb"].shape[1])[None, :] * pr["step"]
                    jin = np.argmin(np.abs(sp - 0.6 * r), axis=1)
                    y_in = (pr["rgb"] @ _Y)[np.arange(len(jin)), jin]
                    lit_dir = _harmonic_dir(phi[usable], y_in[usable]) if usable.sum() >= 6 else 0.0
                    te = rr - cov_crossing(s.coverage, c, phi, float(rr.max() + 6)) if s.coverage is not None else None
                    if te is not None:
                        m = usable & np.isfinite(te)
                        rays["err"].append(te[m])
                        cl = np.cos(phi[m] - lit_dir)
                        rays["lit"].append(te[m][cl > 0.5])
                        rays["dark"].append(te[m][cl < -0.5])
                    # the contact-shadow rays: background darker just beyond the edge than 3 px further
                    rp = blur / (edge_fit.BLUR_PER_WIDTH * edge_fit.DISC_WIDTH_PER_RADIUS) + edge_fit.NEAR_BG_MARGIN_PX
                    ud = d / np.maximum(rr, 1e-9)[:, None]
                    near = _bilinear(ylin, pts + rp * ud)
                    far = _bilinear(ylin, pts + (rp + 3.0) * ud)
                    ok_prod.append(bool(pf.ok))
                    if te is not None:
                        med = max(float(np.median(y_in[usable])), 1e-6) if usable.any() else 1.0
                        feats = np.column_stack([y_in / med, _bilinear(ylin, pts - rp * ud) / med, near / med, far / med,
                                                 near / np.maximum(far, 1e-6), np.cos(phi - lit_dir),
                                                 np.full(len(phi), blur)])
                        per_ball.append(dict(cond=cond, scene=s.hash, pts=pts, use=usable & np.isfinite(te), te=te,
                                             feats=feats, c=c, e=e, axes=(r / sh[0], r), ang=sh[1], ok=bool(pf.ok)))
                    for se in size_errs:
                        f = 1.0 + se / 100.0
                        axes = (f * r / sh[0], f * r)
                        got_v = variants(pts, usable, axes, sh[1], sh, c, phi, lit_dir, te)
                        got_v["fix_nf>=0.9"] = fit_centre(pts, usable & (near >= 0.9 * np.maximum(far, 1e-6)), axes,
                                                          sh[1], c)
                        got_v = {"product": pf.centre_px if pf.ok else None, **got_v}
                        for name, cc in got_v.items():
                            E[se].setdefault(name, []).append(np.nan if cc is None else float(np.linalg.norm(cc - e)))
        ok = np.array(ok_prod)
        err = np.concatenate(rays["err"]) if rays["err"] else np.zeros(0)
        rows[cond] = {"balls": int(len(ok)), "product_accepts": int(ok.sum()),
                      "rays": {"n": int(len(err)), "mean_px": float(np.mean(err)), "rms_px": float(np.sqrt(np.mean(err**2))),
                               "within_0.15_share": float(np.mean(np.abs(err) < 0.15)),
                               "lit_third_mean_px": float(np.mean(np.concatenate(rays["lit"]))),
                               "dark_third_mean_px": float(np.mean(np.concatenate(rays["dark"])))} if len(err) else {},
                      "fits": {str(se): {k: {"fitted": int(np.sum(np.isfinite(v))),
                                             "mean_px": _nanmean(np.array(v)),
                                             "mean_on_product_accepted_px": _nanmean(np.array(v)[ok])}
                                         for k, v in E[se].items()} for se in size_errs}}
    if per_ball:
        for cond, o in regression(per_ball).items():
            rows[cond]["regression"] = o
    return rows


def regression(balls: list) -> dict:
    """Can a ray's edge error be predicted from what the image shows round it? A linear model of
    the error against the true outline (px) on the ray's features (the ball's interior luma, its
    limb's, the background's just beyond the edge and 3 px further, their ratio, all over the
    ball's median interior luma; the cosine to the lamp's side; the frame's blur), fitted on the
    other scenes (leave one scene out, all conditions pooled). Per condition: the rays' error RMS
    before / after the correction, and the centre of the edges so corrected (size fixed to the
    truth) on the balls the product accepts."""
    X = np.concatenate([b["feats"][b["use"]] for b in balls])
    X = np.column_stack([np.ones(len(X)), X])
    T = np.concatenate([b["te"][b["use"]] for b in balls])
    S = np.concatenate([[b["scene"]] * int(b["use"].sum()) for b in balls])
    pred = np.zeros(len(T))
    for sc in np.unique(S):
        m = S == sc
        pred[m] = X[m] @ np.linalg.lstsq(X[~m], T[~m], rcond=None)[0]
    out, k = {}, 0
    for b in balls:
        n = int(b["use"].sum())
        d = b["pts"] - b["c"]
        rr = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        corr = np.zeros(len(rr))
        corr[b["use"]] = pred[k:k + n]
        o = out.setdefault(b["cond"], {"t": [], "p": [], "centre": []})
        o["t"].append(T[k:k + n])
        o["p"].append(pred[k:k + n])
        k += n
        if b["ok"]:
            cc = fit_centre(b["c"] + (rr - corr)[:, None] * d / rr[:, None], b["use"], b["axes"], b["ang"], b["c"])
            o["centre"].append(np.nan if cc is None else float(np.linalg.norm(cc - b["e"])))
    res = {}
    for cond, o in out.items():
        t, p = np.concatenate(o["t"]), np.concatenate(o["p"])
        res[cond] = {"ray_rms_px": float(np.sqrt(np.mean(t**2))), "corrected_rms_px": float(np.sqrt(np.mean((t - p) ** 2))),
                     "corrected_centre_on_accepted_px": _nanmean(np.array(o["centre"]))}
    return res


def drawn_rows() -> list:
    """The drawn tinted ball of ``tests/vision/test_edge_fit_shadow.py`` (a deep contact shadow, a
    limb tinted by the skin; lamp at 20 deg) at three radii and two sub-pixel offsets: centre error
    (px) of the product's fit and of centre-only fits of the exact size (all rays; the lamp's half
    by the interior luma, least squares and :func:`_l1_centre` up to cos > -0.3)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "vision"))
    from test_edge_fit_shadow import _fit, tinted_ball

    rows = []
    for radius in (6.0, 10.0, 16.0):
        for off in ((0.3, 0.6), (0.8, 0.1)):
            size = int(2 * radius + 40)
            centre = np.array([size / 2 + off[0], size / 2 + off[1]])
            img, _ = tinted_ball(centre, radius, size)
            prod = _fit(img, centre, radius)
            ell = ((centre[0] + 0.4, centre[1] - 0.3), (2 * radius + 0.8, 2 * radius + 0.8), 0.0)
            blur = edge_fit.measure_edge_blur(img, [ell]) or edge_fit.BLUR_PROBE_PX
            pts, u = edge_fit._edge_points(img, [ell], blur)[0]
            d = pts - np.array(ell[0])
            phi = np.arctan2(d[:, 1], d[:, 0])
            pr = profiles(img, ell, blur)
            sp = pr["s0"][:, None] + np.arange(pr["rgb"].shape[1])[None, :] * pr["step"]
            j = np.argmin(np.abs(sp - 0.6 * radius), axis=1)
            lit = _harmonic_dir(phi[u], (pr["rgb"] @ _Y)[np.arange(len(j)), j][u])
            ax = (radius, radius)
            got = {"product": prod.centre_px if prod.ok else None, "fix_all": fit_centre(pts, u, ax, 0.0, ell[0]),
                   "lit_fix": fit_centre(pts, u & (np.cos(phi - lit) > 0), ax, 0.0, ell[0]),
                   "lit_L1": _l1_centre(pts, u & (np.cos(phi - lit) > -0.3), ax, 0.0, ell[0])}
            rows.append({"radius_px": radius, "offset_px": off, "lamp_deg": float(np.degrees(lit)),
                         **{k: None if v is None else float(np.linalg.norm(v - centre)) for k, v in got.items()}})
    return rows


def _nanmean(v):
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else float("nan")


def _bilinear(img, p):
    import cv2

    return cv2.remap(img, p[None, :, 0].astype(np.float32), p[None, :, 1].astype(np.float32), cv2.INTER_LINEAR)[0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=1)
    ap.add_argument("--size-err", type=float, nargs="+", default=[0.0, 2.0, -2.0],
                    help="errors of the fixed outline's size, percent (default 0 2 -2)")
    ap.add_argument("--conditions", default=",".join(CONDITIONS))
    ap.add_argument("--json", action="store_true", help="print only the JSON line")
    ap.add_argument("--drawn", action="store_true", help="only the drawn ball of test_edge_fit_shadow.py")
    a = ap.parse_args(argv)
    if a.drawn:
        rows = drawn_rows()
        if not a.json:
            for r in rows:
                print(f"r {r['radius_px']:4.1f} px, offset {r['offset_px']}, lamp found at {r['lamp_deg']:.0f} deg: "
                      + "  ".join(f"{k} {r[k]:.3f}" for k in ("product", "fix_all", "lit_fix", "lit_L1")))
        print(json.dumps(rows))
        return 0
    rows = run(a.frames, [c for c in a.conditions.split(",") if c], a.size_err)
    if not a.json:
        for cond, o in rows.items():
            ry = o["rays"]
            print(f"== {cond}: {o['balls']} whole balls, the product accepts {o['product_accepts']}; per ray vs the "
                  f"true outline: mean {ry['mean_px']:+.2f} px, RMS {ry['rms_px']:.2f}, within 0.15 px "
                  f"{ry['within_0.15_share']:.2f}, lamp's third {ry['lit_third_mean_px']:+.2f}, far third "
                  f"{ry['dark_third_mean_px']:+.2f}")
            if "regression" in o:
                g = o["regression"]
                print(f"   per-ray error regressed on the image (leave one scene out): RMS {g['ray_rms_px']:.2f} -> "
                      f"{g['corrected_rms_px']:.2f} px; centre of the corrected edges, size fixed, on the accepted "
                      f"balls {g['corrected_centre_on_accepted_px']:.3f} px")
            names = list(next(iter(o["fits"].values())))
            print(f"{'centre err px':<14}" + "".join(f"{'size ' + format(float(se), '+g') + ' %':>25}" for se in o["fits"]))
            print(f"{'':<14}" + "".join(f"{'fitted  mean on-accepted':>25}" for _ in o["fits"]))
            for nm in names:
                print(f"{nm:<14}" + "".join(f"{f[nm]['fitted']:>8} {f[nm]['mean_px']:>5.3f} {f[nm]['mean_on_product_accepted_px']:>10.3f}"
                                            for f in o["fits"].values()))
    print(json.dumps(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
