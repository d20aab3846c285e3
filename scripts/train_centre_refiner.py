"""Train the learned centre refiner (``static/centre_refiner.onnx``; issue 28 item 2).

Two steps, two environments (the app never needs PyTorch):

1. ``gather`` (the project's venv): crops and targets from the rendered ``train`` split
   (``$MONOTRACKER_PBR/train``, seeds from 500000, lamps/skin family T: never the tuning or
   held-out splits) and from our simulator (seeds 7000+, never the benchmarks' seeds):

   * ``product``: every ball the product's chain fits (``PoseTracker`` with the edge detector
     and the camera's outlines, as ``benchmarks/camera_pbr.py`` runs it), accepted or refused,
     within half a radius of a whole ball's true centre: crops round the product's own centre
     (+ N(0, 0.03 r) px), so that the network learns the bias the edge fit leaves;
   * ``jitter``: every whole ball, crops round its true centre + N(0, 0.1 r) px (a wider
     range, the network's answer beyond the product's errors);
   * ``sim``: the same round our simulator's visible balls (its four benchmark conditions),
     so that the refiner leaves our sharp renders' centres where the edge fit put them.

   Each crop: a random rotation and mirror of the sampling grid, the radius x U(0.95, 1.05)
   (jitter: U(0.9, 1.1)); the target is the offset to the true ellipse centre in radii, in the
   crop's axes (:func:`monotracker.vision.centre_refiner.image_offset_to_crop`).
2. ``train`` (a venv with CPU PyTorch and onnx, e.g. ``pip install torch onnx numpy``): a
   small CNN (~0.1 M weights), smooth-L1 loss, AdamW with a one-cycle schedule; the first
   ``--val-scenes`` rendered scenes are held back and their RMS error printed per epoch; the
   network goes to ONNX.

Usage:
    PYTHONPATH=app .venv/bin/python scripts/train_centre_refiner.py gather --out /tmp/ref.npz
    /path/to/torch-venv/bin/python scripts/train_centre_refiner.py train --data /tmp/ref.npz \\
        --out static/centre_refiner.onnx
"""

from __future__ import annotations

import argparse
import time

import numpy as np

#: must match monotracker.vision.centre_refiner (checked by gather, written into the npz)
CROP = 32


def gather(a) -> None:
    from monotracker.sim.pbr.frameset import CONDITIONS, default_root, list_scenes
    from monotracker.vision import centre_refiner as cr

    assert cr.CROP == CROP
    rng = np.random.default_rng(a.seed)
    X, Y, G = [], [], []

    def add(img, c, e, r0, scale_jitter, g):
        r = r0 * rng.uniform(1.0 - scale_jitter, 1.0 + scale_jitter)
        ang, mir = rng.uniform(0, 2 * np.pi), bool(rng.integers(2))
        X.append(cr.sample_crop(img, c, r, ang, mir))
        Y.append(cr.image_offset_to_crop((e - c) / r, ang, mir))
        G.append(g)

    t0 = time.perf_counter()
    scenes = list_scenes(default_root() / "train")
    for si, sc in enumerate(scenes):
        tr = sc.truth
        for cond, cd in CONDITIONS.items():
            if cd["kind"] != sc.spec.kind:
                continue
            frames, log = product_detections(sc, cond, a.frames)
            for img, d in zip(frames, log):
                for f in list(d.fiducials) + list(d.rejected):
                    p = np.asarray(f.centre_px, float)
                    dist = np.linalg.norm(tr.ellipse_centres_px - p, axis=1)
                    j = int(np.argmin(dist))
                    if dist[j] > max(2.0, 0.5 * tr.radius_px[j]) or not tr.whole[j]:
                        continue
                    axes = getattr(f, "axes_px", None)
                    r0 = float(min(axes)) if axes is not None and min(axes) > 2 else float(tr.radius_px[j])
                    for _ in range(a.per_ball):
                        add(img, p + rng.normal(0.0, 0.03 * r0, 2), tr.ellipse_centres_px[j], r0, 0.05, si)
                for j in np.flatnonzero(tr.whole):
                    e, r0 = tr.ellipse_centres_px[j], float(tr.radius_px[j])
                    for _ in range(a.jitter_per_ball):
                        add(img, e + rng.normal(0.0, 0.1 * r0, 2), e, r0, 0.1, si)
        print(f"train scene {si + 1}/{len(scenes)}: {len(X)} crops ({time.perf_counter() - t0:.0f} s)", flush=True)
    if a.sim_seeds:
        import sys
        from pathlib import Path

        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
        from camera_pipeline import condition_camera

        for cond in ("clean", "OR", "degraded", "clutter"):
            for sd in range(a.sim_seeds):
                cam = condition_camera(cond, 6.0, 7000 + sd)
                for k in range(a.sim_frames):
                    img, tr = cam.render(k * 6.0 / a.sim_frames)
                    for j in np.flatnonzero(tr.visible):
                        e, r0 = tr.ellipse_centres_px[j], float(tr.radius_px[j])
                        for _ in range(a.sim_per_ball):
                            add(img, e + rng.normal(0.0, 0.1 * r0, 2), e, r0, 0.1, -1 - sd)
            print(f"simulator {cond}: {len(X)} crops ({time.perf_counter() - t0:.0f} s)", flush=True)
    np.savez_compressed(a.out, X=np.array(X, np.float16), Y=np.array(Y, np.float32), G=np.array(G, np.int32),
                        crop=CROP)
    print(f"{a.out}: {len(X)} crops")


def product_detections(sc, cond: str, n_frames: int):
    """(frames, detections) of the product's chain on one rendered scene: the pose tracker with
    the edge detector (which then gets the camera's outlines and the tracker's hints)."""
    from monotracker.sim.pbr.frameset import camera_frames
    from monotracker.vision.detect_classical import ClassicalDetector
    from monotracker.vision.detection import BlobRules
    from monotracker.vision.frames import Frame
    from monotracker.vision.pose_tracker import PoseTracker
    from monotracker.vision.recording import RecordingDetector

    cam, tr = sc.camera_model(), sc.truth
    det = ClassicalDetector(BlobRules(radius_mm=tr.radius_mm, focal_px=float(cam.K[0, 0])))
    rec = RecordingDetector(det)
    frames = camera_frames(sc, cond, n_frames)
    trk = PoseTracker(tr.fiducials_ct, cam, detector=rec, radius_mm=tr.radius_mm, target_ct=tr.target_ct)
    for k, img in enumerate(frames):
        trk.process(Frame(img, k / 30.0, k, None))
    return frames, rec.log


def build(width: int):
    import torch.nn as nn

    w = width

    def block(i, o):
        return [nn.Conv2d(i, o, 3, padding=1), nn.BatchNorm2d(o), nn.ReLU()]

    return nn.Sequential(*block(3, w), *block(w, w), nn.MaxPool2d(2), *block(w, 2 * w), *block(2 * w, 2 * w),
                         nn.MaxPool2d(2), *block(2 * w, 2 * w), nn.Flatten(),
                         nn.Linear(2 * w * (CROP // 4) ** 2, 64), nn.ReLU(), nn.Linear(64, 2))


def train(a) -> None:
    import torch

    torch.manual_seed(a.seed)
    torch.set_num_threads(a.threads)
    ds = [np.load(f) for f in a.data.split(",")]
    assert all(int(d["crop"]) == CROP for d in ds if "crop" in d)
    X = torch.tensor(np.concatenate([d["X"] for d in ds]).astype(np.float32))
    Y = torch.tensor(np.concatenate([d["Y"] for d in ds]))
    G = np.concatenate([d["G"] for d in ds])
    val = np.isin(G, np.unique(G[G >= 0])[: a.val_scenes])
    Xt, Yt, Xv, Yv = X[~val], Y[~val], X[val], Y[val]
    print(f"train {len(Xt)} crops, validation {len(Xv)} ({a.val_scenes} rendered scenes)", flush=True)
    net = build(a.width)
    opt = torch.optim.AdamW(net.parameters(), lr=a.lr, weight_decay=1e-4)
    steps = a.epochs * ((len(Xt) + a.batch - 1) // a.batch)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=a.lr, total_steps=steps)
    t0 = time.perf_counter()
    for ep in range(a.epochs):
        net.train()
        perm = torch.randperm(len(Xt))
        total = 0.0
        for i in range(0, len(Xt), a.batch):
            b = perm[i:i + a.batch]
            loss = torch.nn.functional.smooth_l1_loss(net(Xt[b]), Yt[b], beta=0.02)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss) * len(b)
        net.eval()
        with torch.no_grad():
            pv = torch.cat([net(Xv[i:i + 1024]) for i in range(0, len(Xv), 1024)]) if len(Xv) else Yv
            rv = float((pv - Yv).pow(2).sum(1).mean().sqrt())
        print(f"epoch {ep + 1}: loss {total / len(Xt):.5f}, validation RMS {rv:.4f} r "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    net.eval()
    torch.onnx.export(net, torch.zeros(1, 3, CROP, CROP), a.out, input_names=["crop"], output_names=["offset"],
                      dynamic_axes={"crop": {0: "n"}, "offset": {0: "n"}}, opset_version=17, dynamo=False)
    print(f"wrote {a.out}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("gather", help="crops from the train split and our simulator -> npz")
    g.add_argument("--out", required=True)
    g.add_argument("--frames", type=int, default=4, help="camera frames per scene and condition")
    g.add_argument("--per-ball", type=int, default=8, help="crops per ball the product fitted")
    g.add_argument("--jitter-per-ball", type=int, default=2, help="crops per whole ball round its truth")
    g.add_argument("--sim-seeds", type=int, default=3)
    g.add_argument("--sim-frames", type=int, default=20)
    g.add_argument("--sim-per-ball", type=int, default=2)
    g.add_argument("--seed", type=int, default=0)
    t = sub.add_parser("train", help="npz -> ONNX (needs PyTorch and onnx)")
    t.add_argument("--data", required=True, help="one or more npz files, comma-separated")
    t.add_argument("--out", required=True)
    t.add_argument("--epochs", type=int, default=15)
    t.add_argument("--batch", type=int, default=256)
    t.add_argument("--lr", type=float, default=3e-3)
    t.add_argument("--width", type=int, default=16)
    t.add_argument("--val-scenes", type=int, default=4)
    t.add_argument("--threads", type=int, default=2)
    t.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    {"gather": gather, "train": train}[a.cmd](a)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
