"""Feasibility of a learned ball-centre refiner on physically rendered frames (issue 28).

Train: the ``train`` split's scenes (``$MONOTRACKER_PBR/train``; seeds from 500000, lamps/skin
family T, see ``sim.pbr.spec``), each through the conditions' camera chains
(``frameset.camera_frames``). Each whole ball (>= 98 % visible) gives crops sampled round a
jittered centre (truth + N(0, 0.1 r) px per axis), jittered scale (r x U(0.9, 1.1)) and a random
rotation / mirror of the sampling grid; the target is the offset (crop frame, radius units) from
the crop centre to the true ellipse centre. Model: ridge regression (scikit-learn) on the crop's
normalised colour pixels (``CROP`` x ``CROP`` x 3, half-width ``SPAN`` radii), or ``--model mlp``
(one hidden layer of 64).

Score: the committed TUNING crops only (``tests/data/pbr/tuning``), through the product's chain
(``PoseTracker`` with the edge detector and the camera's outlines, as ``benchmarks/camera_pbr.py``):
on every accepted detection of a whole ball, the centre error (px, carried to the sphere centre
with the true depth, against the true projected sphere centre) today and after the refiner.
Also a validation subset of the train split (scenes held back from fitting).

Usage: PYTHONPATH=app python scripts/learn_centre_refiner.py [--frames 3] [--val 4]
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

from monotracker.sim.pbr.frameset import CONDITIONS, camera_frames, committed_root, default_root, list_scenes
from monotracker.sim.pbr.truth import sphere_centre_px
from train_centre_refiner import product_detections   # scripts/: the product's chain on a rendered scene

CROP = 24
SPAN = 1.7


def crop_features(img: np.ndarray, c, r: float, angle: float = 0.0, mirror: bool = False) -> np.ndarray:
    """CROP x CROP x 3 bilinear samples of BGR ``img`` on a grid centred on ``c`` (px), half-width
    ``SPAN * r`` px, rotated by ``angle`` rad (and mirrored in x), each channel minus its mean,
    all divided by the crop's std; flattened (float32)."""
    u = (np.arange(CROP) + 0.5) / CROP * 2.0 - 1.0
    gx, gy = np.meshgrid(u, u)
    if mirror:
        gx = -gx
    ca, sa = np.cos(angle), np.sin(angle)
    s = SPAN * r
    mx = (c[0] + s * (ca * gx - sa * gy)).astype(np.float32)
    my = (c[1] + s * (sa * gx + ca * gy)).astype(np.float32)
    p = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).astype(np.float32)
    p -= p.reshape(-1, 3).mean(axis=0)
    p /= p.std() + 1e-3
    return p.ravel()


def to_crop_frame(d, angle: float, mirror: bool) -> np.ndarray:
    """Image offset (dx, dy) -> the crop grid's (u, v) (inverse of the grid's rotation/mirror)."""
    ca, sa = np.cos(angle), np.sin(angle)
    u = ca * d[0] + sa * d[1]
    v = -sa * d[0] + ca * d[1]
    return np.array([-u if mirror else u, v])


def train_samples(scenes, n_frames: int, per_ball: int, rng) -> tuple[np.ndarray, np.ndarray]:
    X, Y = [], []
    for sc in scenes:
        tr = sc.truth
        for cond, cd in CONDITIONS.items():
            if cd["kind"] != sc.spec.kind:
                continue
            for img in camera_frames(sc, cond, n_frames):
                for j in np.flatnonzero(tr.whole):
                    e, r0 = tr.ellipse_centres_px[j], float(tr.radius_px[j])
                    for _ in range(per_ball):
                        r = r0 * rng.uniform(0.9, 1.1)
                        c = e + rng.normal(0.0, 0.1 * r0, 2)
                        ang, mir = rng.uniform(0, 2 * np.pi), bool(rng.integers(2))
                        X.append(crop_features(img, c, r, ang, mir))
                        Y.append(to_crop_frame((e - c) / r, ang, mir))
    return np.array(X, np.float32), np.array(Y, np.float32)


def score(scenes, conds, model, n_frames: int) -> dict:
    """Per condition: errors (px) today and refined on accepted detections of whole balls."""
    out = {}
    for cond in conds:
        today, refined, n_acc = [], [], 0
        for sc in scenes:
            if CONDITIONS[cond]["kind"] != sc.spec.kind:
                continue
            tr, cam = sc.truth, sc.camera_model()
            frames, log = product_detections(sc, cond, n_frames)
            for img, d in zip(frames, log):
                for f in d.fiducials:
                    p = np.asarray(f.centre_px, float)
                    dist = np.linalg.norm(tr.ellipse_centres_px - p, axis=1)
                    j = int(np.argmin(dist))
                    if dist[j] > max(2.0, 0.5 * tr.radius_px[j]) or not tr.whole[j]:
                        continue
                    n_acc += 1
                    r = float(min(f.axes_px))
                    q = p + r * model.predict(crop_features(img, p, r)[None])[0]
                    z = tr.fiducials_cam[j, 2:3]
                    for pt, lst in ((p, today), (q, refined)):
                        s = sphere_centre_px(pt[None], z, tr.radius_mm, cam.K, cam.dist)[0]
                        lst.append(float(np.linalg.norm(s - tr.projected_centres_px[j])))
        t, f = np.array(today), np.array(refined)
        out[cond] = {"n": n_acc, **{f"{k}_{s}": (float(np.mean(a)) if s == "mean" else float(np.percentile(a, q)))
                                    if len(a) else float("nan")
                                    for k, a in (("today", t), ("refined", f))
                                    for s, q in (("mean", 0), ("median", 50), ("p90", 90))}}
    return out


def main() -> int:
    from sklearn.linear_model import Ridge

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--per-ball", type=int, default=6)
    ap.add_argument("--val", type=int, default=4, help="train scenes held back for validation")
    ap.add_argument("--alpha", type=float, default=30.0)
    ap.add_argument("--model", choices=("ridge", "mlp"), default="ridge")
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    train = list_scenes(default_root() / "train")
    val, fit = train[: a.val], train[a.val:]
    t0 = time.perf_counter()
    X, Y = train_samples(fit, 2, a.per_ball, rng)
    print(f"train: {len(fit)} scenes, {len(X)} crops ({time.perf_counter() - t0:.0f} s)", flush=True)
    if a.model == "ridge":
        model = Ridge(alpha=a.alpha).fit(X, Y)
    else:
        from sklearn.neural_network import MLPRegressor

        model = MLPRegressor((64,), alpha=1e-3, max_iter=200, early_stopping=True, random_state=0).fit(X, Y)
    print(f"model {a.model}, fitted in {time.perf_counter() - t0:.0f} s since start")
    r = model.predict(X) - Y
    print(f"fit rms residual {np.sqrt(np.mean(r ** 2)):.3f} r (target rms {np.sqrt(np.mean(Y ** 2)):.3f} r)")
    tuning = list_scenes(committed_root() / "tuning")
    for name, scenes in (("train-val", val), ("TUNING", tuning)):
        res = score(scenes, list(CONDITIONS), model, a.frames)
        print(f"{name}: {len(scenes)} scenes, {a.frames} frames; centre error px (accepted whole balls)")
        print(f"  {'cond':<9}{'n':>5}  today mean/med/p90    refined mean/med/p90")
        for c, v in res.items():
            print(f"  {c:<9}{v['n']:>5}  {v['today_mean']:.3f}/{v['today_median']:.3f}/{v['today_p90']:.3f}"
                  f"    {v['refined_mean']:.3f}/{v['refined_median']:.3f}/{v['refined_p90']:.3f}")
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
