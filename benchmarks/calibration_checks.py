"""What a wrong camera calibration does, and which checks see it (issue 36).

Tables (all on the digital twin's camera, 1280x720, f = 1100 px, the OR layout's 450 mm view of
the phantom's 9 balls, unless said otherwise):

1. **The harm.** Frames rendered with the true camera, tracked with a calibration whose focal
   length or principal point is off: share of frames trusted and the error at the planned target
   (mm). Baseline: the right calibration, same frames.
2. **The balls' known size** (``pose_checks.physical_problem``'s test: minor semi-axis vs
   ``f R / z``): median observed / expected ratio under each calibration. Size and depth both
   scale with f, so the ratio stays ~1: this check is blind to it, by physics.
3. **The constellation's own perspective** (``vision.calibration_check.fit_intrinsics``, pooled
   over frames, each frame's pose free): fitted focal length scale and principal point shift, on
   the twin with the CT's fiducial localisation error (0.1 mm per axis, random per scene) and
   without it, and on frames of the independent renderer (``tests/vision/independent_render``):
   the spread with the right calibration is the floor that decides what can be caught.
4. **The start check against a known board** (``vision.calibration_check.check_with_board``):
   chessboards rendered by our ray-plane renderer (``calibration.render_chessboard``, not
   OpenCV's projection) at 350-550 mm, tilted 15-40 deg, blurred and noisy; per number of views
   and per calibration error: share "disagrees" / "agrees" / "inconclusive". The false-alarm
   rate is the "disagrees" share with the right calibration.

Usage: PYTHONPATH=app python benchmarks/calibration_checks.py [--quick]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import cv2
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "vision"))

from monotracker.geometry import apply_transform, make_transform, rotation_about_axis
from monotracker.sim.camera_sim import SimulatedCamera
from monotracker.sim.or_layout import default_layout
from monotracker.sim.trajectories import make_trajectory
from monotracker.vision.calibration import chessboard_views, render_chessboard
from monotracker.vision.calibration_check import check_with_board, fit_intrinsics
from monotracker.vision.camera_model import CameraModel
from monotracker.vision.frames import Frame
from monotracker.vision.pose_tracker import PoseTracker

LAYOUT = default_layout()
PH = LAYOUT.phantom
ERRORS = (("right", 1.0, 0.0), ("f +2 %", 1.02, 0.0), ("f -2 %", 0.98, 0.0), ("f +5 %", 1.05, 0.0),
          ("f +10 %", 1.10, 0.0), ("f +20 %", 1.20, 0.0), ("cx +10 px", 1.0, 10.0), ("cx +20 px", 1.0, 20.0),
          ("cx +40 px", 1.0, 40.0))


def wrong(camera: CameraModel, f_scale: float, dcx: float) -> CameraModel:
    K = camera.K.copy()
    K[0, 0] *= f_scale
    K[1, 1] *= f_scale
    K[0, 2] += dcx
    return CameraModel(K, camera.dist, camera.image_size)


def twin_frames(seed: int, n: int):
    cam = SimulatedCamera(seed=seed, trajectory=make_trajectory("breathing", seed=seed), T_cam_world=LAYOUT.T_cam_ct0)
    return cam.camera, [cam.render(i / 10.0) for i in range(n)]


def track(model, frames, fiducials_ct):
    """Per frame (estimate, truth T) with a fresh tracker."""
    trk = PoseTracker(fiducials_ct, model, radius_mm=PH.fiducial_radius_mm, target_ct=PH.sample_target_lps)
    out = []
    for k, (img, truth) in enumerate(frames):
        out.append((trk.process(Frame(img, truth.t_s, k, truth)), truth.T_cam_ct, trk))
    return out


def table_harm_and_size(scenes: int, n: int) -> None:
    print("\n1-2. A wrong calibration on the twin (true camera renders; tracked with the calibration shown)")
    print(f"{'calibration':>11} {'trusted':>8} {'target err mm (median, max)':>28} {'size ratio (median)':>20}")
    data = [twin_frames(100 + s, n) for s in range(scenes)]
    for label, fs, dcx in ERRORS:
        trusted, errs, ratios = 0, [], []
        for true, frames in data:
            model = wrong(true, fs, dcx)
            for est, T_true, trk in track(model, frames, PH.fiducial_centres_lps):
                if est.T_cam_ct is None:
                    continue
                trusted += est.ok
                t = PH.sample_target_lps
                if est.ok:
                    errs.append(float(np.linalg.norm(apply_transform(est.T_cam_ct, t) - apply_transform(T_true, t))))
                # the size check's ratio: matched balls' minor semi-axes vs f R / z under this calibration
                det = trk.detector.detect(frames[est.frame_index][0])
                z = apply_transform(est.T_cam_ct, PH.fiducial_centres_lps)[:, 2]
                pts = det.centres
                for j in range(len(z)):
                    if not np.all(np.isfinite(est.image_points_px[j])) or len(pts) == 0:
                        continue
                    i = int(np.argmin(np.linalg.norm(pts - est.image_points_px[j], axis=1)))
                    b = min(det.fiducials[i].axes_px)
                    R = PH.fiducial_radius_mm
                    ratios.append(b / (model.K[0, 0] * R / np.sqrt(z[j] ** 2 - R**2)))
        total = scenes * n
        e = f"{np.median(errs):8.2f} {np.max(errs):8.2f}" if errs else f"{'-':>8} {'-':>8}"
        print(f"{label:>11} {trusted:>4}/{total:<3} {e:>28} {np.median(ratios):20.4f}")


def _perturbed(rng, sigma_mm: float) -> np.ndarray:
    return PH.fiducial_centres_lps + rng.normal(0.0, sigma_mm, PH.fiducial_centres_lps.shape)


def table_constellation(scenes: int, n: int) -> None:
    print("\n3. The constellation's perspective: focal length scale and principal point fitted over pooled "
          "frames (right calibration unless said)")
    print(f"{'frames':>14} {'CT err mm':>9} {'balls':>5} {'f scale: mean':>14} {'sd':>7} {'max |f-1|':>9} "
          f"{'dcx px sd':>9} {'noise-only sd %':>15} {'sd@0.25px %':>11}")
    data = [twin_frames(200 + s, n) for s in range(scenes)]
    for ct_sigma in (0.0, 0.1):
        for idx in (list(range(9)), [0, 1, 2, 3, 4]):
            fs, dcs, sd_n, sd_s = [], [], [], []
            for s, (true, frames) in enumerate(data):
                X = _perturbed(np.random.default_rng(300 + s), ct_sigma)[idx]
                obs = [(e.T_cam_ct, e.image_points_px) for e, _T, _t in track(true, frames, X) if e.ok]
                fit = fit_intrinsics(obs, X, true.K, true.dist, PH.fiducial_radius_mm)
                if fit is None:
                    continue
                fs.append(fit.f_scale)
                dcs.append(fit.dc_px[0])
                sd_n.append(fit.std(0.0)[0])
                sd_s.append(fit.std(0.25)[0])
            if not fs:
                print(f"{'twin':>14} {ct_sigma:9.2f} {len(idx):5d}  no scene trusted enough frames")
                continue
            fs = np.array(fs)
            print(f"{'twin ' + str(n):>14} {ct_sigma:9.2f} {len(idx):5d} {fs.mean():14.4f} {100 * fs.std():6.2f}% "
                  f"{100 * np.abs(fs - 1).max():8.2f}% {np.std(dcs):9.1f} {100 * np.median(sd_n):15.2f} "
                  f"{100 * np.median(sd_s):11.2f}   ({len(fs)} scenes)")
    # independent renderer: the pose test's scenes (8 balls on a 90 mm cap at ~420 mm)
    from independent_render import FRAME_K, FRAME_SIZE, Imaging, render_scene
    from test_pose_independent import _scene

    cam = CameraModel(FRAME_K, np.zeros(5), FRAME_SIZE)
    for ct_sigma in (0.0, 0.1):
        fs = []
        for s in range(scenes):
            rng = np.random.default_rng(400 + s)
            X_ct, T, target = _scene(rng)
            X_cam = apply_transform(T, X_ct)
            Xm = X_ct + rng.normal(0.0, ct_sigma, X_ct.shape)
            trk = PoseTracker(Xm, cam, radius_mm=4.0, target_ct=target)
            obs = []
            for i in range(max(4, n // 3)):
                img, _ = render_scene(rng, X_cam, 4.0, Imaging(defocus_px=1.0, gauss_px=0.5, jpeg_quality=0))
                est = trk.process(Frame(img, 0.1 * i, i))
                if est.ok:
                    obs.append((est.T_cam_ct, est.image_points_px))
            fit = fit_intrinsics(obs, Xm, cam.K, cam.dist, 4.0)
            if fit is not None:
                fs.append(fit.f_scale)
        fs = np.array(fs)
        if len(fs):
            print(f"{'independent':>14} {ct_sigma:9.2f} {8:5d} {fs.mean():14.4f} {100 * fs.std():6.2f}% "
                  f"{100 * np.abs(fs - 1).max():8.2f}%   ({len(fs)} scenes)")


def board_views(camera: CameraModel, rng, n_views: int, pattern=(9, 6), square=25.0):
    """Rendered chessboard views of ``camera``: 350-550 mm away, tilted 15-40 deg, 1 px blur and
    grey-level noise 2; returns (obj, img) lists of the views where the board was found."""
    rays = camera.pixel_rays(2)
    obj, img = [], []
    while len(obj) < n_views:          # a view whose board is not found (cut by the image edge) is drawn again
        R = rotation_about_axis(rng.normal(size=3), np.radians(rng.uniform(15, 40)))
        centre = np.array([(pattern[0] - 1) * square / 2, (pattern[1] - 1) * square / 2, 0])
        t = np.array([rng.uniform(-90, 90), rng.uniform(-50, 50), rng.uniform(350, 550)]) - R @ centre
        im = render_chessboard(camera, make_transform(R, t), pattern, square, rays=rays)
        im = cv2.GaussianBlur(im, (0, 0), 0.8).astype(np.float32) + rng.normal(0, 2.0, im.shape)
        o, i, _names, _skipped, _size = chessboard_views([np.clip(np.round(im), 0, 255).astype(np.uint8)], pattern,
                                                        square)
        obj += o
        img += i
    return obj, img


def table_board(trials: int) -> None:
    print("\n4. Start check against a known board (chessboard 9x6, 25 mm): verdicts per calibration error")
    true = SimulatedCamera(seed=0).camera
    cases = (("right", 1.0, 0.0), ("f +0.25 %", 1.0025, 0.0), ("f +0.5 %", 1.005, 0.0), ("f +1 %", 1.01, 0.0),
             ("f -1 %", 0.99, 0.0), ("f +2 %", 1.02, 0.0), ("cx +2.5 px", 1.0, 2.5), ("cx +5 px", 1.0, 5.0),
             ("cx +10 px", 1.0, 10.0))
    print(f"{'views':>5} {'calibration':>11} {'disagrees':>9} {'agrees':>7} {'inconcl.':>8} {'f ratio - 1 (mean)':>19} "
          f"{'3 sd %':>7}")
    for n_views in (1, 3, 5):
        rng = np.random.default_rng(500 + n_views)
        sets = [board_views(true, rng, n_views) for _ in range(trials)]
        for label, fs, dcx in cases:
            model = wrong(true, fs, dcx)
            v, ef, sd = [], [], []
            for obj, img in sets:
                r = check_with_board(model, obj, img)
                v.append(r.verdict)
                ef.append(r.f_ratio - 1)
                sd.append(3 * r.f_std)
            print(f"{n_views:5d} {label:>11} {v.count('disagrees'):>4}/{trials:<4} {v.count('agrees'):>3}/{trials:<3} "
                  f"{v.count('inconclusive'):>3}/{trials:<4} {100 * np.mean(ef):18.3f}% {100 * np.median(sd):6.2f}%")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer scenes and trials")
    ap.add_argument("--tables", default="1,3,4", help="which tables to print (1 = harm and size, 3, 4)")
    args = ap.parse_args()
    scenes, n, trials = (2, 10, 10) if args.quick else (6, 20, 40)
    tables = set(args.tables.split(","))
    print(f"load before: {os.getloadavg()[0]:.2f}")
    t0 = time.perf_counter()
    if "1" in tables:
        table_harm_and_size(scenes, n)
    if "3" in tables:
        table_constellation(scenes, n)
    if "4" in tables:
        table_board(trials)
    print(f"load after: {os.getloadavg()[0]:.2f}")
    print(f"\n({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
