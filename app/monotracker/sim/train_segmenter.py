"""Train the small fiducial segmentation network on simulated frames and export it to ONNX.

Offline tool (needs CPU PyTorch, which is NOT a runtime dependency):

    .venv/bin/pip install torch==2.13.0
    PYTHONPATH=app python -m monotracker.sim.train_segmenter --out static/fiducial_seg.onnx

Data: frames of :class:`~monotracker.sim.camera_sim.SimulatedCamera` with random head poses
(+-20 deg, 420-680 mm), random occluders, many stray green blobs (round ones too), lighting
0.55-1.45, noise 1-5 grey levels and motion blur. Label: the visible-ball coverage
(``truth.fiducial_mask``): balls only, so the network learns to ignore strays and the clip.
Input at half resolution (640x360 for a 1280x720 camera), RGB scaled to [0, 1]; output logits
at quarter resolution (320x180).

Network (a tiny U-Net, ~17 k parameters, ~70 kB as ONNX; sized for ~10 ms on 2 CPU cores):
a stride-2 3x3 stem (8 ch), a block of two 3x3 convs (16 ch), 2x2 max-pool, a block (24 ch),
nearest upsampling with skip concatenation, one 3x3 conv (16 ch), a 1x1 conv to one logit. Trained on 96x96 crops (2/3 of them centred on a
ball or a stray) with binary cross-entropy + soft Dice, Adam, a few minutes on 2 CPU cores.
Seeds are fixed; the script prints the validation IoU at the end.
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

INPUT_SCALE = 0.5
#: the network's output grid relative to the full image (its stem has stride 2)
OUTPUT_SCALE = 0.25


def make_dataset(n_frames: int, seed: int):
    """(images (n, 3, H/2, W/2) float32 RGB [0, 1], labels (n, 1, H/2, W/2) float32, centres list)."""
    from monotracker.geometry import invert_transform, look_at, rotation_about_axis
    from monotracker.sim.camera_sim import SimulatedCamera, Stray, random_events

    rng = np.random.default_rng(seed)
    cam = SimulatedCamera(seed=seed)
    ph = cam.phantom
    patch = cam.fiducials_ct.mean(0)
    xs, ys, cents = [], [], []
    for _i in range(n_frames):
        # random viewpoint around the view direction
        ax = rng.normal(size=3)
        R = rotation_about_axis(ax, np.radians(rng.uniform(0, 20)))
        view = R @ ph.view_direction_lps
        eye = patch + rng.uniform(420, 680) * view
        up = rotation_about_axis(view, rng.uniform(-0.6, 0.6)) @ np.array([0.0, -1.0, 0.0])
        aim = patch + rng.normal(0, 25, 3)
        cam.T_cam_world = invert_transform(look_at(eye, aim, up))
        cam.noise_sigma = rng.uniform(1, 5)
        cam._noise_pos, cam._noise_neg = cam._make_noise(rng, 2)
        cam.exposure_s = 0.0
        px = cam.rest_projection()
        ev = random_events(4.0, px, seed=int(rng.integers(1 << 30)), occlusions=int(rng.integers(0, 3)),
                           strays=0, lighting=False)
        for k in range(int(rng.integers(1, 6))):
            shape = ("round", "irregular", "streak")[k % 3]
            c = px.mean(0) + rng.normal(0, 1, 2) * [260, 160] if rng.random() < 0.6 else rng.uniform([40, 40], [1240, 680])
            ev.strays.append(Stray(0, 10, tuple(c), rng.uniform(5, 20), shape, int(rng.integers(1 << 20))))
        g = rng.uniform(0.55, 1.45)
        ev.lighting = [(0.0, g), (10.0, g)]
        cam.events = ev
        t = rng.uniform(0, 3.9)
        img, tr = cam.render(t, with_mask=True)
        if rng.random() < 0.3:  # motion blur in a random direction
            L = int(rng.integers(2, 6))
            k = np.zeros((L, L), np.float32)
            cv2.line(k, (0, int(rng.integers(L))), (L - 1, int(rng.integers(L))), 1.0)
            img = cv2.filter2D(img, -1, k / k.sum())
        small = cv2.resize(img, None, fx=INPUT_SCALE, fy=INPUT_SCALE, interpolation=cv2.INTER_AREA)
        lab = cv2.resize(tr.fiducial_mask, None, fx=OUTPUT_SCALE, fy=OUTPUT_SCALE, interpolation=cv2.INTER_AREA)
        xs.append(cv2.cvtColor(small, cv2.COLOR_BGR2RGB).transpose(2, 0, 1).astype(np.float32) / 255.0)
        ys.append(lab[None].astype(np.float32))
        pts = list(tr.projected_centres_px[tr.visible_fraction > 0.2] * INPUT_SCALE) + \
            list(tr.stray_centres_px * INPUT_SCALE)
        cents.append(np.array(pts).reshape(-1, 2))
    return np.stack(xs), np.stack(ys), cents


def build_model():
    import torch
    from torch import nn

    def block(cin, cout):
        return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.ReLU(inplace=True),
                             nn.Conv2d(cout, cout, 3, padding=1), nn.ReLU(inplace=True))

    class TinyUNet(nn.Module):
        def __init__(self):
            super().__init__()
            self.stem = nn.Sequential(nn.Conv2d(3, 8, 3, stride=2, padding=1), nn.ReLU(inplace=True))
            self.e1, self.e2 = block(8, 16), block(16, 24)
            self.d1 = nn.Sequential(nn.Conv2d(24 + 16, 16, 3, padding=1), nn.ReLU(inplace=True))
            self.head = nn.Conv2d(16, 1, 1)
            self.pool = nn.MaxPool2d(2)
            self.up = nn.Upsample(scale_factor=2, mode="nearest")

        def forward(self, x):
            a = self.e1(self.stem(x))
            b = self.e2(self.pool(a))
            return self.head(self.d1(torch.cat([self.up(b), a], 1)))

    return TinyUNet()


def _crops(X, Y, cents, n, size, rng):
    H, W = X.shape[2:]
    xb = np.empty((n, 3, size, size), np.float32)
    yb = np.empty((n, 1, size // 2, size // 2), np.float32)
    for i in range(n):
        k = int(rng.integers(len(X)))
        if len(cents[k]) and rng.random() < 0.67:
            c = cents[k][rng.integers(len(cents[k]))] + rng.uniform(-size / 3, size / 3, 2)
        else:
            c = rng.uniform([size / 2, size / 2], [W - size / 2, H - size / 2])
        x0 = int(np.clip(c[0] - size / 2, 0, W - size))
        y0 = int(np.clip(c[1] - size / 2, 0, H - size))
        x0, y0 = x0 // 2 * 2, y0 // 2 * 2
        xb[i] = X[k, :, y0:y0 + size, x0:x0 + size]
        yb[i] = Y[k, :, y0 // 2:y0 // 2 + size // 2, x0 // 2:x0 // 2 + size // 2]
    return xb, yb


def train(out: str, frames: int = 160, steps: int = 1500, seed: int = 0, threads: int = 2) -> dict:
    import torch

    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    rng = np.random.default_rng(seed)
    t0 = time.time()
    X, Y, C = make_dataset(frames, seed)
    Xv, Yv, _ = make_dataset(max(8, frames // 10), seed + 1000)
    print(f"data: {len(X)} train + {len(Xv)} val frames in {time.time() - t0:.0f} s", flush=True)
    model = build_model()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=3e-3, total_steps=steps)
    bce = torch.nn.BCEWithLogitsLoss(pos_weight=torch.tensor(4.0))
    t1 = time.time()
    for step in range(steps):
        xb, yb = _crops(X, Y, C, 16, 96, rng)
        xb, yb = torch.from_numpy(xb), torch.from_numpy(yb)
        logit = model(xb)
        p = torch.sigmoid(logit)
        dice = 1 - (2 * (p * yb).sum() + 1) / (p.sum() + yb.sum() + 1)
        loss = bce(logit, yb) + dice
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 250 == 0 or step == steps - 1:
            print(f"step {step:5d} loss {loss.item():.4f} ({time.time() - t1:.0f} s)", flush=True)
    model.eval()
    with torch.no_grad():
        pv = torch.sigmoid(model(torch.from_numpy(Xv))).numpy()
    inter = np.logical_and(pv > 0.5, Yv > 0.5).sum()
    union = np.logical_or(pv > 0.5, Yv > 0.5).sum()
    iou = float(inter / max(union, 1))
    H, W = X.shape[2:]
    torch.onnx.export(model, torch.zeros(1, 3, H, W), out, input_names=["image"], output_names=["logit"],
                      dynamic_axes={"image": {2: "h", 3: "w"}, "logit": {2: "h", 3: "w"}}, opset_version=17,
                      dynamo=False)
    print(f"validation IoU {iou:.3f}; exported {out}; total {time.time() - t0:.0f} s", flush=True)
    return {"iou": iou, "seconds": time.time() - t0}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=None, help="ONNX path (default static/fiducial_seg.onnx)")
    ap.add_argument("--frames", type=int, default=160)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    if a.out is None:
        from monotracker.paths import static_dir

        static_dir().mkdir(exist_ok=True)
        a.out = str(static_dir() / "fiducial_seg.onnx")
    train(a.out, a.frames, a.steps, a.seed, a.threads)


if __name__ == "__main__":
    main()
