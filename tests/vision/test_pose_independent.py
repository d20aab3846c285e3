"""The whole pose pipeline (detector with the camera's ball outlines, registration, trust gates)
on frames rendered independently of our simulator: 8 spheres of 4 mm on a head-sized cap seen
from ~420 mm, each drawn at its exact image ellipse (``independent_render.render_scene``: the
tangent-cone conic, not our projection code), with real optics (Bayer, noise, blur, JPEG), and
with straight occluders cutting some balls.

Truth: the pose that placed the spheres; the error is measured at a deep target (the head's
centre, 90 mm below the balls). Wrong-but-valid (trusted with more than 2 mm at the target) must
never happen; whole-ball frames must be trusted and right (< 1 mm)."""

from __future__ import annotations

import numpy as np
from independent_render import FRAME_K, FRAME_SIZE, Imaging, Occluder, render_scene, sphere_image_ellipse

from monotracker.geometry import apply_transform
from monotracker.vision.camera_model import CameraModel
from monotracker.vision.frames import Frame
from monotracker.vision.pose_tracker import PoseTracker

CAMERA = CameraModel(FRAME_K, np.zeros(5), FRAME_SIZE)
RADIUS_MM = 4.0
SHARP_RAW = Imaging(defocus_px=0.0, gauss_px=0.4, jpeg_quality=0)
BLURRED_JPEG = Imaging(defocus_px=1.5, gauss_px=0.5, jpeg_quality=85)
OCCLUDERS = ("blue glove", "steel", "white gauze", "blue drape")


def _scene(rng):
    """(fiducials_ct (8, 3) mm, T_cam_ct (4, 4), target_ct (3,)): balls on the camera-facing cap
    (within 70 deg) of a 90 mm sphere around the CT origin (the target), the head ~420 mm away,
    turned up to 15 deg; drawn until the balls' 96 px patches do not overlap and lie >= 60 px
    inside the frame."""
    from scipy.spatial.transform import Rotation

    while True:
        dirs = []
        while len(dirs) < 8:
            v = rng.normal(size=3)
            v /= np.linalg.norm(v)
            if -v[2] > np.cos(np.radians(70)):
                dirs.append(v)
        X_ct = 90.0 * np.array(dirs)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.uniform(-1, 1, 3) * np.radians(15) / np.sqrt(3)).as_matrix()
        T[:3, 3] = [rng.uniform(-60, 60), rng.uniform(-30, 30), 420.0 + rng.uniform(-30, 30)]
        c = np.array([sphere_image_ellipse(x, RADIUS_MM)[0] for x in apply_transform(T, X_ct)])
        inside = np.all((c > 60) & (c < np.array(FRAME_SIZE) - 60))
        gaps = np.abs(c[:, None] - c[None]).max(axis=2) + 1e6 * np.eye(8)    # Chebyshev px
        if inside and gaps.min() >= 100:
            return X_ct, T, np.zeros(3)


def _run(imaging, n_cut: int, frames: int, seed: int):
    """Per frame (trusted, error at the target mm, reason)."""
    rng = np.random.default_rng(seed)
    X_ct, T, target = _scene(rng)
    trk = PoseTracker(X_ct, CAMERA, radius_mm=RADIUS_MM, target_ct=target)
    X_cam = apply_transform(T, X_ct)
    out = []
    for i in range(frames):
        cut = rng.choice(8, n_cut, replace=False)
        occ = {int(k): Occluder(float(rng.uniform(0.2, 0.35)), OCCLUDERS[(i + j) % len(OCCLUDERS)])
               for j, k in enumerate(cut)}
        img, _ = render_scene(rng, X_cam, RADIUS_MM, imaging, occ)
        est = trk.process(Frame(img, 0.1 * i, i))
        err = (float(np.linalg.norm(apply_transform(est.T_cam_ct, target) - apply_transform(T, target)))
               if est.ok else float("nan"))
        out.append((est.ok, err, est.reason))
    return out


def test_whole_balls_give_a_trusted_right_pose():
    """Every frame trusted; error at the target 0.002-0.042 mm here and with seeds 4-5 (bound
    0.25 mm, the product's "right" is 1 mm)."""
    for imaging in (SHARP_RAW, BLURRED_JPEG):
        res = _run(imaging, n_cut=0, frames=4, seed=3)
        assert all(ok for ok, _e, _r in res), [r for ok, _e, r in res if not ok]
        assert max(e for _ok, e, _r in res) < 0.25


def test_cut_balls_never_give_a_wrong_trusted_pose():
    """Two of eight balls cut by occluders (20-35 % of the radius) in every frame: each frame is
    trusted and right, or refused; never trusted with more than 2 mm at the target. Seeds 4-6:
    5-6 of 6 frames trusted (the first may be refused: its noise estimate has few degrees of
    freedom), mean error 0.024-0.053 mm, worst 0.091 mm; with the free ellipse (the detector
    without the camera) 0.025-0.074 mm, worst 0.27 mm: with eight balls a cut ball's bias
    mostly costs centre accuracy, little pose accuracy."""
    for imaging in (SHARP_RAW, BLURRED_JPEG):
        res = _run(imaging, n_cut=2, frames=6, seed=4)
        trusted = [e for ok, e, _r in res if ok]
        assert all(e < 2.0 for e in trusted)
        assert len(trusted) >= 4 and np.mean(trusted) < 0.25
