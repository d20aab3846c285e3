"""Ball centres on frames rendered independently of our simulator (issue 13, item 1's judge).

``tests/vision/independent_render.py`` renders one ball per 96 x 96 image: supersampled
analytic ellipse of known centre, Lambert + Phong shading, a background of one or two colours
(the boundary within a radius of the centre: a ball on the head's outline), a defocus disc PSF
plus a Gaussian, Bayer + OpenCV's bilinear demosaicing, shot and read noise, the sRGB curve and
JPEG via OpenCV. It shares no code with ``monotracker.sim``.

Prints, per imaging condition and background, per detector (the classical detector with
``chroma`` centres: the baseline; ``edge-line``: the edge fit as of issue 13's round 4, each
ray's background the line through its two outer eighths; ``edge``: today's default, the near
background, see ``edge_fit.NEAR_BACKGROUND``; ``edge-r5``: that fit with the unmixing's residual
tolerance 0.12 whatever the blur, before ``edge_fit.SHARP_UNMIX_RESIDUAL``; ``edge+ref``: ``edge``
with the learned centre refiner, opt-in, issue 28; ``edge+shade``: ``edge`` with the opt-in shading
shift, ``vision/shading_shift.py``; ``trim``: ``edge`` with the opt-in second score of a blob
refused for its shape, its thin parts cut off, ``BlobRules.trim_tails``; ``smooth``: ``edge``
with the opt-in third look in blurred frames, ``ClassicalDetector.mask_smooth_per_blur`` 1.0), mean and p95 centre error (px) of the balls found
within 3 px, recall, the mean error on the balls all edge fits accept (``common``), and the
edge blur the fit measured. Then the edge fit with the blur-per-width factor at other values
(see ``edge_fit.BLUR_PER_WIDTH``), over both backgrounds. Then balls cut by a straight occluder
(15-35 % of the radius hidden: a glove, an instrument, gauze, skin, drapes) and whole balls, each
pasted into a 1280 x 720 frame at a random place with the outline a sphere has there
(``independent_render.render_in_frame``): ``edge-free`` the detector without the camera (a free
ellipse per ball, the fit before ``vision/sphere_outline.py``) vs ``edge`` with it (and ``edge+ref``, ``edge+shade``, ``trim``, ``smooth``), same frames:
balls accepted, accepted more than 0.5 px off, worst and mean error.

Usage: PYTHONPATH=app python benchmarks/independent_optics.py [--quick] [--n N]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace

import cv2
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "vision"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from camera_pipeline import EDGE_R5, EdgeSettings
from independent_render import (FRAME_F_PX, FRAME_K, FRAME_SIZE, Imaging, Occluder, render_ball,
                                render_in_frame)

from monotracker.vision import edge_fit
from monotracker.vision.camera_model import CameraModel
from monotracker.vision.centre_refiner import CentreRefiner
from monotracker.vision.detect_classical import ClassicalDetector
from monotracker.vision.detection import BlobRules

OCCLUDERS = ("blue glove", "steel", "white gauze", "fair skin", "blue drape", "teal drape")

CONDITIONS = {
    "sharp, raw": Imaging(defocus_px=0.0, gauss_px=0.4, jpeg_quality=0),
    "blur 1.5, JPEG 85": Imaging(defocus_px=1.5, gauss_px=0.5, jpeg_quality=85),
    "blur 2.5, JPEG 70, noisy": Imaging(defocus_px=2.5, gauss_px=0.7, jpeg_quality=70, full_well_e=2000.0,
                                        read_noise_e=8.0, exposure=0.5),
}

#: the edge fit as of issue 13's round 4: each ray's background the line through its two outer
#: eighths
EDGE_LINE = dict(NEAR_BACKGROUND=False)


def scenes(n: int, seed: int, imaging: Imaging, split: bool) -> list:
    rng = np.random.default_rng(seed)
    return [render_ball(rng, float(rng.uniform(6.0, 14.0)), imaging, split=split) for _ in range(n)]


def evaluate(det, frames) -> tuple:
    """(per frame the centre error px of the ball, NaN where not found within 3 px; median CPU
    ms per frame)."""
    errs, cpu = np.full(len(frames), np.nan), []
    for i, (img, c) in enumerate(frames):
        t0 = time.process_time()
        d = det.detect(img)
        cpu.append(time.process_time() - t0)
        if len(d.centres):
            e = np.linalg.norm(np.asarray(d.centres) - c, axis=1).min()
            if e < 3.0:
                errs[i] = e
    return errs, 1000 * float(np.median(cpu))


def _stats(e: np.ndarray) -> tuple:
    """(mean px, p95 px, recall) of per-frame errors (NaN = not found)."""
    ok = ~np.isnan(e)
    if not ok.any():
        return np.nan, np.nan, 0.0
    return float(e[ok].mean()), float(np.percentile(e[ok], 95)), float(ok.mean())


def measured_blur(frames) -> float:
    """Median of the edge blur (px) the fit measures on these frames."""
    det = ClassicalDetector()
    out = []
    for img, _c in frames:
        m = det.mask(img)
        cnts, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cnts = [c for c in cnts if len(c) >= 5]
        if cnts:
            b = edge_fit.measure_edge_blur(img, [cv2.fitEllipse(max(cnts, key=len))])
            if b is not None:
                out.append(b)
    return float(np.median(out)) if out else float("nan")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer balls per cell (40)")
    ap.add_argument("--n", type=int, default=None, help="balls per cell (default 150, quick 40)")
    ap.add_argument("--seed", type=int, default=11)
    a = ap.parse_args(argv)
    n = a.n or (40 if a.quick else 150)
    print(f"independent renders: {n} balls per cell, radius 6-14 px, load {os.getloadavg()[0]:.1f}")
    dets = [("chroma", ClassicalDetector(centre_method="chroma")),
            ("edge-line", EdgeSettings(ClassicalDetector(), **EDGE_LINE)),
            ("edge-r5", EdgeSettings(ClassicalDetector(), **EDGE_R5)),
            ("edge", ClassicalDetector()), ("edge+ref", ClassicalDetector(refiner=CentreRefiner())),
            ("edge+shade", ClassicalDetector(BlobRules(shading_shift=True))),
            ("trim", ClassicalDetector(BlobRules(trim_tails=True)))]
    print(f"{'condition':<26} {'background':<10} {'detector':<9} {'err mean':>8} {'err p95':>7} {'recall':>6} "
          f"{'common':>6} {'cpu ms':>6} {'blur px':>7}")
    for ci, (cname, im) in enumerate(CONDITIONS.items()):
        for split in (False, True):
            frames = scenes(n, a.seed + 10 * ci + split, im, split)
            blur = measured_blur(frames)
            res = {dname: evaluate(det, frames) for dname, det in dets}
            both = np.all([~np.isnan(e) for d, (e, _ms) in res.items() if d != "chroma"], axis=0)
            for dname, (e, ms) in res.items():
                mean, p95, rec = _stats(e)
                common = f"{e[both].mean():6.3f}" if dname != "chroma" and both.any() else f"{'':>6}"
                print(f"{cname:<26} {'two-colour' if split else 'one colour':<10} {dname:<9} {mean:8.3f} {p95:7.3f} "
                      f"{rec:6.3f} {common} {ms:6.1f} {blur:7.2f}")
    print("\nBlur per width (edge_fit.BLUR_PER_WIDTH), edge detector, one- and two-colour backgrounds "
          "together: err mean / recall")
    factors = (0.6, 0.85, 1.1, 1.3)
    print(f"{'condition':<26} " + " ".join(f"{f:>13.2f}" for f in factors))
    for ci, (cname, im) in enumerate(CONDITIONS.items()):
        frames = scenes(n, a.seed + 10 * ci, im, False) + scenes(n, a.seed + 10 * ci + 1, im, True)
        cells = []
        for f in factors:
            mean, _p95, rec = _stats(evaluate(EdgeSettings(ClassicalDetector(), BLUR_PER_WIDTH=f), frames)[0])
            cells.append(f"{mean:6.3f} / {rec:4.2f}")
        print(f"{cname:<26} " + " ".join(f"{c:>13}" for c in cells))
    cut_table(n, a.seed)
    print(f"(load at the end {os.getloadavg()[0]:.1f})")


def cut_table(n: int, seed: int) -> None:
    """Cut and whole balls in frames, the detector without and with the camera (see the module
    docstring)."""
    cam = CameraModel(FRAME_K, np.zeros(5), FRAME_SIZE)
    rules = BlobRules(radius_mm=4.0, focal_px=FRAME_F_PX, min_distance_mm=250.0)
    dets = (("edge-free", ClassicalDetector(rules)),
            ("edge", ClassicalDetector(replace(rules, camera=cam))),
            ("edge+ref", ClassicalDetector(replace(rules, camera=cam), refiner=CentreRefiner())),
            ("edge+shade", ClassicalDetector(replace(rules, camera=cam, shading_shift=True))),
            ("trim", ClassicalDetector(replace(rules, camera=cam, trim_tails=True))),
            ("smooth", ClassicalDetector(replace(rules, camera=cam), mask_smooth_per_blur=1.0)))
    print(f"\nCut balls (15-35 % of the radius hidden) and whole balls in 1280 x 720 frames, {n} per cell")
    print(f"{'condition':<26} {'balls':<6} {'detector':<9} {'accepted':>8} {'> 0.5 px':>8} {'worst px':>8} "
          f"{'mean px':>7}")
    for ci, (cname, im) in enumerate(CONDITIONS.items()):
        for cut in (True, False):
            rng = np.random.default_rng(seed + 100 + 10 * ci + cut)
            frames = [render_in_frame(rng, im, Occluder(float(rng.uniform(0.15, 0.35)), OCCLUDERS[i % len(OCCLUDERS)])
                                      if cut else None) for i in range(n)]
            for dname, det in dets:
                e = evaluate(det, frames)[0]
                ok = ~np.isnan(e)
                worst = f"{e[ok].max():8.2f}" if ok.any() else f"{'-':>8}"
                mean = f"{e[ok].mean():7.3f}" if ok.any() else f"{'-':>7}"
                print(f"{cname:<26} {'cut' if cut else 'whole':<6} {dname:<9} {int(ok.sum()):8d} "
                      f"{int(np.sum(e[ok] > 0.5)):8d} {worst} {mean}")


if __name__ == "__main__":
    main()
