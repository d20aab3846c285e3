"""Prototype (issue 28 item 2): per-ray edge locators against the 50 %-coverage crossing on the
committed tuning crops (tests/data/pbr/tuning, the Mitsuba coverage image beside each crop).

Per whole ball: rays from its true ellipse centre (the edge fit's own layout and blur), the
product's edge per ray, alternative locators from the same profiles, the true edge (last 0.5
crossing of the rendered coverage along the ray); per-ray error split by the ball's lit / dark
side and by a darkening background (contact shadow); per ball the known-shape fit's centre error.

Usage: PYTHONPATH=app python scripts/edge_locators.py [--frames N]
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

W = edge_fit.COLOUR_WEIGHTS


def profiles(img, ell, blur):
    e, (counts, boxes, _w_in, step_b, phi, s0) = edge_fit._ray_layout(img, [ell], blur)
    if counts[0] == 0:
        return None
    k = edge_fit.SAMPLES
    x0, y0, x1, y1 = boxes[0]
    cx, cy = e[0, 0], e[0, 1]
    lin = edge_fit.LINEAR_LUT[img[y0:y1, x0:x1]]
    s = s0[:, None] + (np.arange(k) * step_b[0])[None, :]
    mx = (cx - x0 + s * np.cos(phi)[:, None]).astype(np.float32)
    my = (cy - y0 + s * np.sin(phi)[:, None]).astype(np.float32)
    rgb = cv2.remap(lin, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)    # (n, k, 3) linear BGR
    return dict(rgb=rgb, phi=phi, s0=s0, step=float(step_b[0]), c=np.array([cx, cy]))


def cov_crossing(cov, c, phi, s_max):
    """Per ray: distance (px) from c to the last 0.5 crossing of coverage along the ray."""
    s = np.arange(0.0, s_max, 0.02)
    mx = (c[0] + s[None, :] * np.cos(phi)[:, None]).astype(np.float32)
    my = (c[1] + s[None, :] * np.sin(phi)[:, None]).astype(np.float32)
    v = cv2.remap(cov, mx, my, cv2.INTER_LINEAR)
    out = np.full(len(phi), np.nan)
    for n in range(len(phi)):
        above = np.flatnonzero(v[n] >= 0.5)
        if not len(above) or above[-1] + 1 >= len(s):
            continue
        j = above[-1]
        g0, g1 = v[n, j], v[n, j + 1]
        out[n] = s[j] + 0.02 * (g0 - 0.5) / max(g0 - g1, 1e-9)
    return out


def _win_mean(P, lo, hi, step):
    """Mean of P (n, k, c) over sample positions [lo, hi) px from the ray start (per ray)."""
    k = P.shape[1]
    j = np.arange(k)[None, :] * step
    w = ((j >= lo[:, None]) & (j < hi[:, None])).astype(np.float32)
    w[w.sum(1) == 0, 0] = 1.0
    return (P * w[..., None]).sum(1) / w.sum(1)[:, None]


def local_plateau(P, x0, step, blur, margin=0.5, width=1.0, iters=2, mode="proj", Wm=None):
    """Edge (px from ray start) from local plateaus round x0: ball B just inside, background G just
    outside (beyond the PSF radius), coverage a = projection of (p - G) on (B - G) (mode proj),
    or a of p = a B + beta g (background brightness free, mode bgfree); edge = lo + integral a."""
    if Wm is not None:
        P = P @ Wm.T
    k = P.shape[1]
    r_psf = blur / (edge_fit.BLUR_PER_WIDTH * edge_fit.DISC_WIDTH_PER_RADIUS)
    x = x0.copy()
    s = np.arange(k) * step
    for _ in range(iters):
        lo = np.maximum(x - r_psf - margin, 0.0)
        hi = np.minimum(x + r_psf + margin, (k - 1) * step)
        B = _win_mean(P, np.maximum(lo - width, 0.0), np.maximum(lo, step * 1.01), step)
        G = _win_mean(P, hi, hi + width, step)
        if mode == "proj":
            d = B - G
            a = np.einsum("nkc,nc->nk", P - G[:, None], d) / np.maximum((d * d).sum(1), 1e-12)[:, None]
        else:   # p = a B + beta g
            g = G / np.maximum(np.linalg.norm(G, axis=1, keepdims=True), 1e-12)
            Bp = B - (B * g).sum(1, keepdims=True) * g      # B orthogonal to g
            a = np.einsum("nkc,nc->nk", P, Bp) / np.maximum((Bp * Bp).sum(1), 1e-12)[:, None]
        a = np.clip(a, 0.0, 1.0)
        inwin = (s[None, :] >= lo[:, None]) & (s[None, :] <= hi[:, None])
        # samples j_lo..j_hi each stand for step px: the edge = (j_lo - 1/2) step + sum a x step
        jlo = np.ceil(lo / step - 1e-9)
        x = (jlo - 0.5) * step + (a * inwin).sum(1) * step
    return x


def _peak_position(prof, step):
    """(n,) position along each ray (px) of the largest sample of ``prof`` (n, k) (-inf outside
    the search window), refined to a parabola through it and its neighbours."""
    k = prof.shape[1]
    j = np.clip(np.argmax(prof, 1), 1, k - 2)
    r = np.arange(len(j))
    y0, y1, y2 = prof[r, j - 1], prof[r, j], prof[r, j + 1]
    y0 = np.where(np.isfinite(y0), y0, y1)
    y2 = np.where(np.isfinite(y2), y2, y1)
    den = y0 - 2 * y1 + y2
    off = np.where(np.abs(den) > 1e-12, 0.5 * (y0 - y2) / np.where(np.abs(den) > 1e-12, den, 1), 0.0)
    return (j + np.clip(off, -1, 1)) * step


def steepest(P, x0, step, blur, Wm=None):
    """Position of the steepest change of the local ball->background projection (parabola peak)."""
    if Wm is not None:
        P = P @ Wm.T
    k = P.shape[1]
    r_psf = blur / (edge_fit.BLUR_PER_WIDTH * edge_fit.DISC_WIDTH_PER_RADIUS)
    s = np.arange(k) * step
    lo = np.maximum(x0 - r_psf - 0.5, 0.0)
    hi = np.minimum(x0 + r_psf + 0.5, (k - 1) * step)
    B = _win_mean(P, np.maximum(lo - 1.0, 0.0), np.maximum(lo, step * 1.01), step)
    G = _win_mean(P, hi, hi + 1.0, step)
    d = B - G
    a = np.einsum("nkc,nc->nk", P - G[:, None], d) / np.maximum((d * d).sum(1), 1e-12)[:, None]
    da = -np.gradient(a, axis=1)
    da[(s[None, :] < lo[:, None]) | (s[None, :] > hi[:, None])] = -np.inf
    return _peak_position(da, step)


def chroma_steep(rgb, x0, step, blur, lo_px=3.0, hi_px=1.0, sigma_px=0.0, far_bg=True):
    """Steepest descent of the ball's chromaticity share along the ray, searched in [x0 - lo_px,
    x0 + hi_px]: q = p / sum(p) (linear BGR), h = (q - q_bg) . (q_ball - q_bg) / |..|^2, with
    q_ball the median over the ray's inner samples and q_bg the ray's outer eighth."""
    k = rgb.shape[1]
    q = rgb / np.maximum(rgb.sum(2, keepdims=True), 1e-6)
    nin = max(k // 10, 3)
    qb = np.median(q[:, :nin], axis=1)
    qb = np.repeat(np.median(qb, axis=0, keepdims=True), len(qb), 0)   # the ball's, all rays
    qg = q[:, k - k // 8:].mean(1)
    d = qb - qg
    h = np.einsum("nkc,nc->nk", q - qg[:, None], d) / np.maximum((d * d).sum(1), 1e-12)[:, None]
    if sigma_px > 0:
        j = np.arange(k)
        ker = np.exp(-0.5 * ((j[:, None] - j[None, :]) * step / sigma_px) ** 2)
        ker /= ker.sum(1, keepdims=True)
        h = h @ ker.T
    s = np.arange(k) * step
    dh = -np.gradient(h, axis=1)
    bad = (s[None, :] < (x0 - lo_px)[:, None]) | (s[None, :] > (x0 + hi_px)[:, None])
    dh[bad] = -np.inf
    return _peak_position(dh, step)


def hybrid(rgb, x0, step, blur, margin=0.2, sigma_px=1.0, q="median"):
    """The product's edge, but no further out than the chroma edge + the ball's median offset
    between the two (+ margin px): the contact shadow's outward excursion clipped."""
    xc = chroma_steep(rgb, x0, step, blur, sigma_px=sigma_px)
    off = np.median(x0 - xc) if q == "median" else np.percentile(x0 - xc, q)
    return np.minimum(x0, xc + off + margin)


def first_step(rgb, x0, step, blur, cw=1.0, frac=0.35, lo_px=3.0, hi_px=1.0, sigma_px=0.7):
    """The innermost local maximum of the colour gradient's magnitude (luma and colour differences
    weighted ``cw``, relative to the pixel's brightness) in [x0 - lo_px, x0 + hi_px] that reaches
    ``frac`` of the window's largest: the ball's own edge, before a shadow's ramp further out."""
    P = rgb @ chroma_weights(cw).T
    k = P.shape[1]
    j = np.arange(k)
    ker = np.exp(-0.5 * ((j[:, None] - j[None, :]) * step / sigma_px) ** 2)
    ker /= ker.sum(1, keepdims=True)
    Ps = np.einsum("jk,nkc->njc", ker, P)
    bright = np.maximum(Ps[..., 0], 1e-4)
    g = np.sqrt((np.gradient(Ps, axis=1) ** 2).sum(2)) / bright
    s = j * step
    bad = (s[None, :] < (x0 - lo_px)[:, None]) | (s[None, :] > (x0 + hi_px)[:, None])
    g[bad] = 0.0
    gmax = g.max(1, keepdims=True)
    peak = np.zeros_like(g, bool)
    peak[:, 1:-1] = (g[:, 1:-1] >= g[:, :-2]) & (g[:, 1:-1] >= g[:, 2:]) & (g[:, 1:-1] >= frac * gmax)
    jm = np.where(peak.any(1), np.argmax(peak, 1), np.argmax(g, 1))
    jm = np.clip(jm, 1, k - 2)
    r = np.arange(len(jm))
    y0, y1, y2 = g[r, jm - 1], g[r, jm], g[r, jm + 1]
    den = y0 - 2 * y1 + y2
    off = np.where(np.abs(den) > 1e-12, 0.5 * (y0 - y2) / np.where(np.abs(den) > 1e-12, den, 1), 0.0)
    return (jm + np.clip(off, -1, 1)) * step


def chroma_weights(cw):
    return np.array([[0.114, 0.587, 0.299],
                     [cw * 0.886, -cw * 0.587, -cw * 0.299],
                     [-cw * 0.114, -cw * 0.587, cw * 0.701]], np.float32)


LOCATORS = {
    "local_proj": lambda P, rgb, x0, st, bl: local_plateau(P, x0, st, bl),
    "local_proj_c3": lambda P, rgb, x0, st, bl: local_plateau(rgb, x0, st, bl, Wm=chroma_weights(3.0)),
    "local_bgfree": lambda P, rgb, x0, st, bl: local_plateau(P, x0, st, bl, mode="bgfree"),
    "steep": lambda P, rgb, x0, st, bl: steepest(P, x0, st, bl),
    "chroma_steep": lambda P, rgb, x0, st, bl: chroma_steep(rgb, x0, st, bl, sigma_px=1.0),
    "first_step": lambda P, rgb, x0, st, bl: first_step(rgb, x0, st, bl),
    "first_step_f5": lambda P, rgb, x0, st, bl: first_step(rgb, x0, st, bl, frac=0.5),
    "first_step_c3": lambda P, rgb, x0, st, bl: first_step(rgb, x0, st, bl, cw=3.0),
    "first_step_abs": lambda P, rgb, x0, st, bl: first_step(rgb, x0, st, bl, cw=0.35),
    "clip_m0": lambda P, rgb, x0, st, bl: hybrid(rgb, x0, st, bl, margin=0.0),
    "clip_m3": lambda P, rgb, x0, st, bl: hybrid(rgb, x0, st, bl, margin=0.3),
}


def run(frames: int, conds):
    scenes = list_scenes(committed_root() / "tuning")
    rows = {}
    for cond in conds:
        spec = CONDITIONS[cond]
        R = {name: {"err": [], "side": [], "nf": [], "ball_err": [], "cut": []} for name in ["product", *LOCATORS]}
        for s in scenes:
            if s.spec.kind != spec["kind"] or s.coverage is None:
                continue
            cam, tr = s.camera_model(), s.truth
            whole = np.flatnonzero(tr.whole)
            for img in camera_frames(s, cond, frames):
                ells, shapes = [], []
                for j in whole:
                    e, r = tr.ellipse_centres_px[j], float(tr.radius_px[j])
                    sh = expected_shapes(cam, [e], [r])[0] or (1.0, 0.0)
                    ells.append(((float(e[0]), float(e[1])), (2 * r / sh[0], 2 * r), float(sh[1])))
                    shapes.append(sh)
                blur = edge_fit.measure_edge_blur(img, ells) or edge_fit.BLUR_PROBE_PX
                pts_all = edge_fit._edge_points(img, ells, blur)
                y = (edge_fit.LINEAR_LUT[img] @ np.array([0.114, 0.587, 0.299], np.float32)).astype(np.float32)
                for ell, sh, got in zip(ells, shapes, pts_all):
                    if got is None:
                        continue
                    pr = profiles(img, ell, blur)
                    pts, usable = got
                    c, phi, s0, st = pr["c"], pr["phi"], pr["s0"], pr["step"]
                    u = np.stack([np.cos(phi), np.sin(phi)], 1)
                    x_prod = ((pts - c) * u).sum(1) - s0
                    truth = cov_crossing(s.coverage, c, phi, float(s0.max() + st * edge_fit.SAMPLES + 2))
                    # lit / dark side of the ball: its luma half way in vs its median there
                    pin = c + (0.55 * (x_prod + s0))[:, None] * u
                    inner = cv2.remap(y, pin[None, :, 0].astype(np.float32), pin[None, :, 1].astype(np.float32),
                                      cv2.INTER_LINEAR)[0]
                    side = np.where(inner >= np.median(inner), 1, -1)
                    rp = blur / (edge_fit.BLUR_PER_WIDTH * edge_fit.DISC_WIDTH_PER_RADIUS) + edge_fit.NEAR_BG_MARGIN_PX
                    pe = c + (x_prod + s0)[:, None] * u
                    near = cv2.remap(y, (pe[:, 0] + rp * u[:, 0]).astype(np.float32)[None],
                                     (pe[:, 1] + rp * u[:, 1]).astype(np.float32)[None], cv2.INTER_LINEAR)[0]
                    far = cv2.remap(y, (pe[:, 0] + (rp + 3) * u[:, 0]).astype(np.float32)[None],
                                    (pe[:, 1] + (rp + 3) * u[:, 1]).astype(np.float32)[None], cv2.INTER_LINEAR)[0]
                    nf = near / np.maximum(far, 1e-6)
                    P = pr["rgb"] @ W.T
                    ok = usable & np.isfinite(truth)
                    for name in ["product", *LOCATORS]:
                        x = x_prod if name == "product" else LOCATORS[name](P, pr["rgb"], x_prod, st, blur)
                        err = (x + s0) - truth
                        R[name]["err"].append(err[ok])
                        R[name]["side"].append(side[ok])
                        R[name]["nf"].append(nf[ok])
                        p2 = c + (x + s0)[:, None] * u
                        fit = edge_fit._robust_ellipse(p2, usable, sh) if usable.sum() >= 0.6 * len(usable) else None
                        if fit is None:
                            R[name]["ball_err"].append(np.nan)
                            R[name]["cut"].append(True)
                        else:
                            R[name]["ball_err"].append(float(np.linalg.norm(np.array(fit[0][0]) - c)))
                            R[name]["cut"].append(bool(edge_fit._hidden_arc(p2, usable, fit[0], sh, blur)))
        out = {}
        for name, d in R.items():
            err = np.concatenate(d["err"])
            side = np.concatenate(d["side"])
            nf = np.concatenate(d["nf"])
            be = np.array(d["ball_err"])
            out[name] = {
                "rays": int(len(err)), "mean": float(err.mean()), "mae": float(np.abs(err).mean()),
                "lit": float(err[side > 0].mean()), "dark": float(err[side < 0].mean()),
                "shadow(nf<0.9)": float(err[nf < 0.9].mean()), "p90abs": float(np.percentile(np.abs(err), 90)),
                "balls": int(len(be)), "ball_err": float(np.nanmean(be)), "cut": int(np.sum(d["cut"])),
            }
        rows[cond] = out
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=1)
    ap.add_argument("--conditions", default="clean,OR,degraded,clutter")
    a = ap.parse_args(argv)
    rows = run(a.frames, a.conditions.split(","))
    for cond, out in rows.items():
        print(f"== {cond}")
        print(f"{'locator':<18} {'rays':>5} {'mean':>6} {'mae':>6} {'lit':>6} {'dark':>6} {'shadow':>6} {'p90':>5} "
              f"{'balls':>5} {'c.err':>6} {'cut':>4}")
        for name, o in out.items():
            print(f"{name:<18} {o['rays']:>5} {o['mean']:>+6.2f} {o['mae']:>6.2f} {o['lit']:>+6.2f} {o['dark']:>+6.2f} "
                  f"{o['shadow(nf<0.9)']:>+6.2f} {o['p90abs']:>5.2f} {o['balls']:>5} {o['ball_err']:>6.3f} {o['cut']:>4}")
    print(json.dumps(rows))


if __name__ == "__main__":
    sys.exit(main())
