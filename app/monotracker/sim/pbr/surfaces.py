"""Meshes, curves and textures of a physically based scene (numpy only; no renderer here).

Everything is in CT LPS millimetres. Meshes are ``(vertices (n, 3), normals (n, 3), uv (n, 2),
faces (m, 3) int)``; normals are analytic where the surface is (the head ellipsoid), else
averaged face normals. Textures are linear RGB float32 arrays (h, w, 3) in [0, 1].
"""

from __future__ import annotations

import cv2
import numpy as np

from monotracker.sim.phantom import HeadPhantom

from .spec import DRAPE_RGB, SceneSpec, _perp_frame, _unit


def _grid_faces(nu: int, nv: int, wrap_u: bool) -> np.ndarray:
    """Two triangles per cell of an (nv, nu) vertex grid (row-major), optionally closed in u."""
    cols = nu if wrap_u else nu - 1
    i, j = np.meshgrid(np.arange(nv - 1), np.arange(cols), indexing="ij")
    a = i * nu + j
    b = i * nu + (j + 1) % nu
    c = (i + 1) * nu + j
    d = (i + 1) * nu + (j + 1) % nu
    return np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)]).astype(
        np.int32)


def _vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N = np.zeros_like(V)
    for k in range(3):
        np.add.at(N, F[:, k], fn)
    return N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)


def head_mesh(ph: HeadPhantom, nu: int = 400, nv: int = 200):
    """The phantom's skin ellipsoid as a triangle mesh with analytic normals. The mesh's pole
    axis lies across the fiducial patch (not through it), so the patch has no seam or pole;
    ``u`` runs round that axis, ``v`` from pole to pole (texture of 2:1 aspect). Vertices lie on
    the ellipsoid; chords between them sag < 0.01 mm at this resolution (0.9 deg steps)."""
    v_dir = _unit(ph.view_direction_lps)
    pole, e2 = _perp_frame(v_dir)
    e1 = v_dir
    a = np.asarray(ph.skin_semi_axes_mm, float)
    th = np.linspace(1e-3, np.pi - 1e-3, nv)
    phi = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    TH, PH = np.meshgrid(th, phi, indexing="ij")
    dirs = (np.cos(TH)[..., None] * pole + np.sin(TH)[..., None] * (np.cos(PH)[..., None] * e1
                                                                  + np.sin(PH)[..., None] * e2)).reshape(-1, 3)
    t = 1.0 / np.sqrt(np.sum(dirs**2 / a**2, axis=1))
    V = ph.centre_lps + t[:, None] * dirs
    N = (V - ph.centre_lps) / a**2
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    uv = np.stack([PH.ravel() / (2 * np.pi), TH.ravel() / np.pi], -1)
    F = _grid_faces(nu, nv, wrap_u=True)
    return V, N, uv, F


def _fold_noise(rng: np.random.Generator, x: np.ndarray, y: np.ndarray, amp: float, n: int = 6) -> np.ndarray:
    """Sum of ``n`` random sinusoidal folds (mm) over coordinates x, y (mm)."""
    out = np.zeros_like(x)
    for _ in range(n):
        ang = rng.uniform(0, np.pi)
        lam = rng.uniform(40.0, 160.0)
        ph = rng.uniform(0, 2 * np.pi)
        w = x * np.cos(ang) + y * np.sin(ang)
        out += amp * rng.uniform(0.3, 1.0) / np.sqrt(n) * np.sin(2 * np.pi * w / lam + ph)
    return out


def drape_sheet(ph: HeadPhantom, seed: int, size_mm: float = 4000.0, n: int = 1024):
    """A folded sheet behind the head, perpendicular to the patch normal, 95 mm below the head
    centre (the head's extent that way is ~84 mm): the background of the head's outline. Flat
    geometry (one rectangle: a folded mesh cost the path tracer 3x more) with the folds in its
    shading normals: (to_world 4x4 of a Mitsuba ``rectangle`` [-1, 1]^2, tangent-space normal
    map (n, n, 3) in [0, 1])."""
    rng = np.random.default_rng(seed)
    v = _unit(ph.view_direction_lps)
    e1, e2 = _perp_frame(v)
    M = np.eye(4)
    M[:3, :3] = np.column_stack([e1 * size_mm / 2, e2 * size_mm / 2, v])
    M[:3, 3] = ph.centre_lps - 95.0 * v
    s = np.linspace(-size_mm / 2, size_mm / 2, n)
    X, Y = np.meshgrid(s, s, indexing="xy")
    h = _fold_noise(rng, X, Y, 14.0)
    step = size_mm / (n - 1)
    gy, gx = np.gradient(h, step)
    nrm = np.stack([-gx, -gy, np.ones_like(h)], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    return M, ((nrm + 1.0) / 2.0).astype(np.float32)


def towel_band(ph: HeadPhantom, seed: int, polar_deg: tuple = (60.0, 100.0), nu: int = 240, nv: int = 32):
    """A folded towel round the head below the fiducial patch: the band of directions
    ``polar_deg`` from the patch normal (about the head centre), lying 1.5 mm above the skin at
    its inner edge and up to ~14 mm further out, with folds."""
    rng = np.random.default_rng(seed + 1)
    v = _unit(ph.view_direction_lps)
    e1, e2 = _perp_frame(v)
    th = np.radians(np.linspace(*polar_deg, nv))
    phi = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    TH, PH = np.meshgrid(th, phi, indexing="ij")
    dirs = np.cos(TH)[..., None] * v + np.sin(TH)[..., None] * (np.cos(PH)[..., None] * e1 + np.sin(PH)[..., None] * e2)
    a = np.asarray(ph.skin_semi_axes_mm, float)
    d = dirs.reshape(-1, 3)
    t = 1.0 / np.sqrt(np.sum(d**2 / a**2, axis=1))
    P = ph.centre_lps + t[:, None] * d
    Nsk = (P - ph.centre_lps) / a**2
    Nsk /= np.linalg.norm(Nsk, axis=1, keepdims=True)
    frac = ((TH - th[0]) / (th[-1] - th[0])).ravel()
    folds = np.zeros(nu)
    for _ in range(5):
        folds += rng.uniform(0.5, 2.0) * np.sin(rng.integers(3, 14) * phi + rng.uniform(0, 2 * np.pi))
    off = 1.5 + 10.0 * frac + np.clip(np.tile(folds, nv), -3, 4) * np.minimum(frac * 4, 1.0)
    V = P + off[:, None] * Nsk
    uv = np.stack([PH.ravel() / (2 * np.pi), frac], -1)
    F = _grid_faces(nu, nv, wrap_u=True)
    N = _vertex_normals(V, F)
    N *= np.sign(np.sum(N * Nsk, axis=1))[:, None]
    return V, N, uv, F


def _fbm(rng: np.random.Generator, shape: tuple, scales: tuple, weights: tuple) -> np.ndarray:
    """Band-limited noise (float32 (h, w), ~zero mean): Gaussian-blurred white noise at each
    scale (px), weighted."""
    out = np.zeros(shape, np.float32)
    for s, w in zip(scales, weights):
        g = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), s, borderType=cv2.BORDER_REFLECT)
        out += w * g / (g.std() + 1e-9)
    return out


def skin_texture(spec: SceneSpec, size: tuple = (2048, 1024)) -> np.ndarray:
    """Linear RGB skin albedo (h, w, 3) for the head mesh's uv (texel ~0.25 mm on the patch):
    low-frequency blotches, pores (small darker dots), and per family: A freckles, B a mottled
    red-brown variation."""
    w, h = size
    rng = np.random.default_rng(spec.skin.texture_seed)
    base = np.array(spec.skin.base_rgb, np.float32)
    blotch = _fbm(rng, (h, w), (40.0, 12.0, 3.0), (0.06, 0.04, 0.025))
    img = base[None, None, :] * (1.0 + blotch[..., None])
    redness = _fbm(rng, (h, w), (20.0, 6.0), (1.0, 0.5))
    img[..., 0] *= 1.0 + 0.05 * redness
    pores = np.zeros((h, w), np.float32)
    n_pores = int(0.02 * w * h)
    ys, xs = rng.integers(0, h, n_pores), rng.integers(0, w, n_pores)
    pores[ys, xs] = rng.uniform(0.3, 1.0, n_pores)
    pores = cv2.GaussianBlur(pores, (0, 0), 0.8)
    img *= (1.0 - 0.5 * np.clip(pores, 0, 1))[..., None]
    if spec.skin.family == "A" or (spec.skin.family == "T" and spec.skin.texture_seed % 2 == 0):
        spots = np.zeros((h, w), np.float32)
        for _ in range(int(0.0004 * w * h)):
            cv2.circle(spots, (int(rng.integers(w)), int(rng.integers(h))), int(rng.integers(2, 6)),
                       float(rng.uniform(0.2, 0.6)), -1, cv2.LINE_AA)
        spots = cv2.GaussianBlur(spots, (0, 0), 1.5)
        img *= 1.0 - spots[..., None] * np.array([0.25, 0.4, 0.5], np.float32)
    else:
        mottle = _fbm(rng, (h, w), (8.0, 2.5), (1.0, 0.6))
        img *= 1.0 + 0.07 * mottle[..., None] * np.array([0.6, 1.0, 1.2], np.float32)
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def drape_texture(names: tuple, seed: int, size: int = 1024) -> np.ndarray:
    """Linear RGB drape albedo (size, size, 3): panels of the named colours split by slanted
    seams, a woven fabric's fine noise."""
    rng = np.random.default_rng(seed + 2)
    img = np.empty((size, size, 3), np.float32)
    img[:] = DRAPE_RGB[names[0]]
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    for name in names[1:]:
        ang = rng.uniform(0, np.pi)
        p = rng.uniform(0.3 * size, 0.7 * size, 2)
        side = (xx - p[0]) * np.sin(ang) - (yy - p[1]) * np.cos(ang) > 0
        img[side] = DRAPE_RGB[name]
    weave = _fbm(rng, (size, size), (0.7, 2.0), (0.03, 0.02))
    return np.clip(img * (1.0 + weave[..., None]), 0.0, 1.0).astype(np.float32)


def plain_texture(name: str, seed: int, size: int = 256) -> np.ndarray:
    rng = np.random.default_rng(seed + 3)
    weave = _fbm(rng, (size, size), (0.7, 2.0), (0.03, 0.02))
    return np.clip(np.array(DRAPE_RGB[name], np.float32) * (1.0 + weave[..., None]), 0, 1).astype(np.float32)


def hair_curves(spec: SceneSpec, ph: HeadPhantom) -> list[np.ndarray]:
    """Hair strands as polylines (k, 3) CT mm lying on the scalp: ``hair_strands`` rooted at
    48-62 deg from the patch normal (the edge of the shaved patch), combed outwards with some
    spread; ``hair_loose`` loose strands anywhere on the patch. Strands 12-45 mm, lifted 0.05-0.4
    mm off the skin, radius :data:`HAIR_RADIUS_MM`."""
    rng = np.random.default_rng(spec.hair_seed)
    v = _unit(ph.view_direction_lps)
    e1, e2 = _perp_frame(v)
    a = np.asarray(ph.skin_semi_axes_mm, float)
    out = []
    n_total = spec.hair_strands + spec.hair_loose
    for k in range(n_total):
        loose = k >= spec.hair_strands
        th = np.radians(rng.uniform(0.0, 40.0) if loose else rng.uniform(48.0, 62.0))
        phi = rng.uniform(0, 2 * np.pi)
        d = np.cos(th) * v + np.sin(th) * (np.cos(phi) * e1 + np.sin(phi) * e2)
        p, n = ph.skin_point(d)
        outward = _unit((np.cos(phi) * e1 + np.sin(phi) * e2) - ((np.cos(phi) * e1 + np.sin(phi) * e2) @ n) * n)
        ang = rng.uniform(0, 2 * np.pi) if loose else rng.normal(0.0, 0.7)
        side = np.cross(n, outward)
        t = _unit(np.cos(ang) * outward + np.sin(ang) * side)
        length = rng.uniform(12.0, 45.0)
        steps = max(4, int(length / 3.0))
        lift = rng.uniform(0.05, 0.4)
        bend = rng.normal(0.0, 0.06)
        pts = []
        q = p
        for _ in range(steps + 1):
            c = q - ph.centre_lps
            s = 1.0 / np.sqrt(np.sum((c / np.linalg.norm(c)) ** 2 / a**2))
            nq = (ph.centre_lps + s * c / np.linalg.norm(c) - ph.centre_lps) / a**2
            nq = _unit(nq)
            on = ph.centre_lps + s * c / np.linalg.norm(c)
            pts.append(on + lift * nq)
            t = _unit(t - (t @ nq) * nq)
            t = _unit(t + bend * np.cross(nq, t))
            q = on + (length / steps) * t
        out.append(np.array(pts))
    return out


#: hair radius (mm): 70 um hair
HAIR_RADIUS_MM = 0.035
