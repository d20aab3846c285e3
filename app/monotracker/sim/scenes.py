"""Synthetic 2D-3D registration scenes with exact ground truth.

A scene is one camera looking at fiducial spheres on a head: CT fiducial centres (mm, LPS),
the true ``T_cam_ct``, intrinsics (1280 x 720, f ~ 1100 px), optional OpenCV distortion, and
the observed image points: projected centres (or, with ``ellipse_bias``, the exact centres of
the ellipses the spheres project to), distorted, with Gaussian pixel noise, some fiducials
occluded, stray blobs added, all shuffled. ``truth_pairs`` lists (image index, fiducial index)
for the points that are fiducials; ``targets_ct`` are deep targets 60-80 mm below the
fiducial patch (along the inward view direction) for TRE.

Camera placement: distance 400-700 mm from the fiducial centroid, viewing direction within
``max_tilt_deg`` of the patch's outward direction, random roll, and the centroid placed
anywhere in the central 60 % of the image.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monotracker.geometry import invert_transform, look_at, rotation_about_axis
from monotracker.sim.phantom import default_phantom

IMAGE_SIZE = (1280, 720)


@dataclass
class Scene:
    fiducials_ct: np.ndarray          # (n, 3) mm
    T_cam_ct: np.ndarray              # 4x4
    K: np.ndarray
    dist: np.ndarray | None
    image_points: np.ndarray          # (m, 2) px, shuffled
    truth_pairs: list                 # [(image_idx, fiducial_idx)]
    stray_indices: list               # image indices that are stray blobs
    targets_ct: np.ndarray            # (k, 3) mm deep targets
    radius_mm: float
    image_size: tuple = IMAGE_SIZE
    info: dict = field(default_factory=dict)


def default_K(f: float = 1100.0, size=IMAGE_SIZE) -> np.ndarray:
    return np.array([[f, 0, size[0] / 2 - 0.5], [0, f, size[1] / 2 - 0.5], [0, 0, 1.0]])


def head_like_layout(rng: np.random.Generator, n: int = 9, max_angle_deg: float = 45.0,
                     min_sep_mm: float = 15.0) -> np.ndarray:
    """n sphere centres on the phantom's scalp at random directions within ``max_angle_deg``
    of its view direction, pairwise at least ``min_sep_mm`` apart (CT mm)."""
    ph = default_phantom()
    v = ph.view_direction_lps
    e1 = np.cross(v, [0, 0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(v, e1)
    pts = []
    while len(pts) < n:
        th = np.radians(max_angle_deg) * np.sqrt(rng.uniform())
        ph_ = rng.uniform(0, 2 * np.pi)
        d = np.cos(th) * v + np.sin(th) * (np.cos(ph_) * e1 + np.sin(ph_) * e2)
        p, nn = ph.skin_point(d)
        c = p + ph.fiducial_radius_mm * nn
        if all(np.linalg.norm(c - q) >= min_sep_mm for q in pts):
            pts.append(c)
    return np.array(pts)


def ellipse_centre_normalised(X_cam: np.ndarray, radius_mm: float) -> np.ndarray:
    """Exact centre of the image ellipse of spheres (centres X_cam (k, 3) mm, radius R) on the
    normalised plane. Derived independently from the cone tangent to the sphere: the
    silhouette is the conic x^T (c c^T - (|c|^2 - R^2) I) x = 0 (x = (u, v, 1)); its centre
    solves the conic's 2x2 linear system."""
    out = []
    for c in np.asarray(X_cam, float):
        Q = np.outer(c, c) - (c @ c - radius_mm**2) * np.eye(3)
        A = Q[:2, :2]
        b = Q[:2, 2]
        out.append(-np.linalg.solve(A, b))
    return np.array(out)


def _to_pixels(xy: np.ndarray, K: np.ndarray, dist) -> np.ndarray:
    """Normalised points -> distorted pixels through OpenCV's own model (cv2.projectPoints),
    independent of the registration package's implementation."""
    import cv2

    P = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    d = np.zeros(5) if dist is None else np.asarray(dist, float)
    px, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, d)
    return px.reshape(-1, 2)


def make_scene(rng: np.random.Generator, layout: str | np.ndarray = "phantom", n_occluded: int = 0,
               n_stray: int = 0, noise_px: float = 0.3, ellipse_bias: bool = False,
               distortion: bool = True, distance_mm: tuple = (400.0, 700.0), max_tilt_deg: float = 35.0,
               fiducial_ids=None, f: float = 1100.0, n_random: int = 9) -> Scene:
    """One random scene; see the module docstring. ``layout``: "phantom" (the 9 phantom
    fiducials, or ``fiducial_ids`` of them), "random" (``n_random`` head-like) or an array."""
    ph = default_phantom()
    if isinstance(layout, str) and layout == "phantom":
        X = ph.fiducial_centres_lps
        if fiducial_ids is not None:
            X = X[list(fiducial_ids)]
    elif isinstance(layout, str) and layout == "random":
        X = head_like_layout(rng, n_random)
    else:
        X = np.asarray(layout, float)
    n = len(X)
    R = ph.fiducial_radius_mm
    centroid = X.mean(axis=0)
    K = default_K(f)
    W, H = IMAGE_SIZE
    for _ in range(200):
        # camera direction within max_tilt of the view direction
        v = ph.view_direction_lps
        axis = np.cross(v, rng.normal(size=3))
        d = rotation_about_axis(axis, np.radians(max_tilt_deg) * np.sqrt(rng.uniform())) @ v
        dist_mm = rng.uniform(*distance_mm)
        eye = centroid + dist_mm * d
        up = rotation_about_axis(d, rng.uniform(-np.pi, np.pi)) @ np.cross(d, np.cross([0, 0, 1.0], d))
        if np.linalg.norm(up) < 1e-6:
            continue
        T_ct_cam = look_at(eye, centroid, up)
        T = invert_transform(T_ct_cam)
        # shift so the centroid lands anywhere in the central 60 % of the image
        target_px = np.array([rng.uniform(0.2, 0.8) * W, rng.uniform(0.2, 0.8) * H])
        ray = np.linalg.solve(K, [target_px[0], target_px[1], 1.0])
        ray /= np.linalg.norm(ray)
        zc = (T @ np.append(centroid, 1))[:3]
        Rsh = _rotation_between(zc / np.linalg.norm(zc), ray)
        T = np.block([[Rsh, np.zeros((3, 1))], [np.zeros((1, 3)), 1]]) @ T
        Xc = X @ T[:3, :3].T + T[:3, 3]
        dist = np.array([-0.12, 0.08, 0.0005, -0.0004, -0.02]) * rng.uniform(0.5, 1.5) if distortion else None
        xy = ellipse_centre_normalised(Xc, R) if ellipse_bias else Xc[:, :2] / Xc[:, 2:3]
        px = _to_pixels(xy, K, dist)
        inside = (px[:, 0] > 10) & (px[:, 0] < W - 10) & (px[:, 1] > 10) & (px[:, 1] < H - 10)
        if inside.all():
            break
    else:
        raise RuntimeError("could not place the camera")
    px = px + rng.normal(scale=noise_px, size=px.shape) if noise_px > 0 else px
    visible = np.sort(rng.choice(n, size=n - n_occluded, replace=False))
    obs = [px[i] for i in visible]
    labels = [int(i) for i in visible]
    lo = px.min(axis=0) - 40
    hi = px.max(axis=0) + 40
    while len(obs) < len(visible) + n_stray:
        s = rng.uniform(lo, hi)
        if np.min(np.linalg.norm(px - s, axis=1)) > 12 and all(np.linalg.norm(s - o) > 12 for o in obs):
            obs.append(s)
            labels.append(-1)
    perm = rng.permutation(len(obs))
    obs = np.array(obs)[perm]
    labels = [labels[i] for i in perm]
    truth = [(k, lab) for k, lab in enumerate(labels) if lab >= 0]
    strays = [k for k, lab in enumerate(labels) if lab < 0]
    # deep targets: 60-80 mm inward from the fiducial patch, spread laterally +-20 mm
    v = ph.view_direction_lps
    targets = []
    for depth in (60.0, 70.0, 80.0):
        for off in ((0, 0), (20, 0), (0, 20), (-20, -20)):
            e1 = np.cross(v, [0, 0, 1.0]); e1 /= np.linalg.norm(e1)
            e2 = np.cross(v, e1)
            targets.append(centroid - depth * v + off[0] * e1 + off[1] * e2)
    return Scene(fiducials_ct=X, T_cam_ct=T, K=K, dist=dist, image_points=obs, truth_pairs=truth,
                 stray_indices=strays, targets_ct=np.array(targets), radius_mm=R,
                 info={"distance_mm": float(np.linalg.norm(zc)), "noise_px": noise_px})


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    v = np.cross(a, b)
    s = np.linalg.norm(v)
    c = float(a @ b)
    if s < 1e-12:
        return np.eye(3)
    return rotation_about_axis(v, np.arctan2(s, c))
