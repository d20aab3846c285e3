"""``method="paper"``: the pipeline of Chen et al. 2025, section 2.2.2-2.2.3, made explicit.

1. **Correspondence** (Eq. 7-10). Image points (undistorted, normalised plane) are KD-ordered
   (:mod:`.kdtree_order`) and turned into adjacent-vector features V_i = P_{i+1} - P_i. The
   CT fiducials are rotated by R(alpha, beta, gamma) = Rz(gamma) Ry(beta) Rx(alpha) (alpha,
   beta choose the viewing direction, gamma spins about it), projected *orthographically*
   onto the x-y plane (the paper's choice; it ignores perspective), KD-ordered the same way and
   featurised. Loss F = sum ||V_img,i - V_model,i||^2 over [-pi, pi]^3, minimised by particle
   swarm optimisation (PSO, vectorised over particles).
   *Scale* (the paper is silent; pixels vs mm): both point sets are centred and scaled to unit
   RMS radius before featurising. Correspondence = i-th image point in KD order <-> i-th
   model point in KD order of the best particle.
2. **Depth** (Eq. 11-12). Q_cam,i = z_i [x_i, y_i, 1] (z the depth along the optical axis); a
   second PSO chooses z_1..z_n minimising sum (||Q_vir,i - Q_vir,i+1|| - ||Q_cam,i -
   Q_cam,i+1||)^2 over KD-adjacent pairs (the paper's loss; ``depth_pairs="all"`` uses every
   pair instead). Search box (the paper gives none): z in [0.6, 1.6] x z0, with z0 =
   (model RMS radius in mm) / (image RMS radius, normalised) from stage 1.
3. **Pose**: Kabsch/SVD between the CT fiducials and Q_cam (the paper's result, kept in
   ``stats["T_svd"]``), then our common Levenberg-Marquardt refinement of the reprojection
   error over all pairs (the issue asks every method to end with it).

The paper's method assumes the image holds exactly the CT's fiducials: with m != n it refuses
(``ok=False``); with occlusion or strays it is simply not applicable. Both PSOs use a seeded
generator (``rng_seed``) so results are reproducible. Integrated loop: the paper runs the two
stages "in an integrated loop"; we re-run both stages with a new seed (up to 3 times) while
the refined pose fails the acceptance gate, then let the common checks judge.
"""

from __future__ import annotations

import time

import numpy as np

from .kabsch import kabsch
from .kdtree_order import kd_order
from .pnp import refine_pose

PSO_W, PSO_C1, PSO_C2 = 0.72, 1.49, 1.49


def _normalise(P: np.ndarray) -> np.ndarray:
    """Centre (..., n, 2) point sets and scale each to unit RMS radius."""
    c = P - P.mean(axis=-2, keepdims=True)
    r = np.sqrt(np.mean(np.sum(c**2, axis=-1), axis=-1))[..., None, None]
    return c / np.maximum(r, 1e-12)


def _features(P: np.ndarray, order: np.ndarray) -> np.ndarray:
    Q = np.take_along_axis(P, order[..., None], axis=-2)
    return np.diff(Q, axis=-2)


def euler_rotations(a: np.ndarray) -> np.ndarray:
    """R = Rz(gamma) Ry(beta) Rx(alpha) for angles a (B, 3) -> (B, 3, 3)."""
    ca, cb, cg = np.cos(a.T)
    sa, sb, sg = np.sin(a.T)
    R = np.empty((len(a), 3, 3))
    R[:, 0, 0] = cg * cb
    R[:, 0, 1] = cg * sb * sa - sg * ca
    R[:, 0, 2] = cg * sb * ca + sg * sa
    R[:, 1, 0] = sg * cb
    R[:, 1, 1] = sg * sb * sa + cg * ca
    R[:, 1, 2] = sg * sb * ca - cg * sa
    R[:, 2, 0] = -sb
    R[:, 2, 1] = cb * sa
    R[:, 2, 2] = cb * ca
    return R


def pso(loss, lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator, particles: int = 60,
        iterations: int = 120, init: np.ndarray | None = None):
    """Minimise ``loss`` (B, d) -> (B,) in the box [lo, hi] by a standard global-best PSO.
    Returns (best position (d,), best loss)."""
    d = len(lo)
    x = rng.uniform(lo, hi, size=(particles, d))
    if init is not None:
        x[0] = init
    span = hi - lo
    v = rng.uniform(-span, span, size=(particles, d)) * 0.1
    f = loss(x)
    pbest, pf = x.copy(), f.copy()
    g = pbest[np.argmin(pf)].copy()
    gf = pf.min()
    for _ in range(iterations):
        r1 = rng.uniform(size=(particles, d))
        r2 = rng.uniform(size=(particles, d))
        v = PSO_W * v + PSO_C1 * r1 * (pbest - x) + PSO_C2 * r2 * (g - x)
        v = np.clip(v, -0.5 * span, 0.5 * span)
        x = np.clip(x + v, lo, hi)
        f = loss(x)
        better = f < pf
        pbest[better], pf[better] = x[better], f[better]
        k = np.argmin(pf)
        if pf[k] < gf:
            g, gf = pbest[k].copy(), pf[k]
    return g, gf


def paper_correspondence(X: np.ndarray, xn: np.ndarray, rng: np.random.Generator, particles=60, iterations=120):
    """Stage 1: returns (pairs [(image, model)], best angles, loss, model/image scale ratio)."""
    img = _normalise(xn)
    img_order = kd_order(img)
    V_img = _features(img, img_order)

    def loss(a):
        R = euler_rotations(a)
        P = np.einsum("bij,kj->bki", R[:, :2, :], X)
        Pn = _normalise(P)
        V = _features(Pn, kd_order(Pn))
        return np.sum((V - V_img) ** 2, axis=(1, 2))

    lo, hi = np.full(3, -np.pi), np.full(3, np.pi)
    a, fa = pso(loss, lo, hi, rng, particles, iterations)
    R = euler_rotations(a[None])[0]
    P = X @ R[:2, :].T
    mod_order = kd_order(_normalise(P))
    pairs = [(int(img_order[i]), int(mod_order[i])) for i in range(len(X))]
    rm = np.sqrt(np.mean(np.sum((P - P.mean(0)) ** 2, 1)))
    ri = np.sqrt(np.mean(np.sum((xn - xn.mean(0)) ** 2, 1)))
    return pairs, a, fa, rm / max(ri, 1e-12)


def paper_depths(Xo: np.ndarray, xo: np.ndarray, z0: float, rng: np.random.Generator, depth_pairs="adjacent",
                 particles=60, iterations=150):
    """Stage 2: depths z (n,) of the ordered image points xo (n, 2) given ordered model Xo."""
    n = len(Xo)
    if depth_pairs == "adjacent":
        I, J = np.arange(n - 1), np.arange(1, n)
    else:
        I, J = np.triu_indices(n, 1)
    dv = np.linalg.norm(Xo[I] - Xo[J], axis=1)
    rays = np.concatenate([xo, np.ones((n, 1))], axis=1)

    def loss(z):
        Q = z[:, :, None] * rays[None]
        dc = np.linalg.norm(Q[:, I] - Q[:, J], axis=2)
        return np.sum((dv - dc) ** 2, axis=1)

    lo, hi = np.full(n, 0.6 * z0), np.full(n, 1.6 * z0)
    z, fz = pso(loss, lo, hi, rng, particles, iterations, init=np.full(n, z0))
    return z * 1.0, fz, rays * z[:, None]


def paper_register(X, xn, fxy, radius_mm, opts, rng_seed: int = 0, depth_pairs: str = "adjacent",
                   attempts: int = 3):
    """Run the paper pipeline. Returns (pairs, refinement | None, stats, reason).

    "Integrated loop" (our reading of the paper): the two PSO stages are re-run with a fresh
    seed, up to ``attempts`` times, while the refined pose does not pass the acceptance gate
    (RMS <= ``opts.accept_rms_px``); the last attempt is returned for the common checks.
    """
    stats: dict = {}
    if len(xn) != len(X):
        return (), None, stats, (f"paper method needs exactly one image point per CT fiducial "
                                 f"({len(xn)} image points, {len(X)} fiducials)")
    out = ((), None, stats, "paper method found no pose")
    for attempt in range(attempts):
        out = _paper_once(X, xn, fxy, radius_mm, np.random.default_rng(rng_seed + 7919 * attempt), depth_pairs)
        out[2]["attempts"] = attempt + 1
        ref = out[1]
        if ref is not None and np.sqrt(np.mean(np.sum(ref.residuals**2, axis=1))) <= opts.accept_rms_px:
            break
    return out


def _paper_once(X, xn, fxy, radius_mm, rng, depth_pairs):
    stats: dict = {}
    t0 = time.perf_counter()
    pairs, angles, floss, z0 = paper_correspondence(X, xn, rng)
    t1 = time.perf_counter()
    ii = np.array([p[0] for p in pairs])
    mi = np.array([p[1] for p in pairs])
    z, fz, Q = paper_depths(X[mi], xn[ii], z0, rng, depth_pairs)
    T_svd = kabsch(X[mi], Q)
    t2 = time.perf_counter()
    stats.update(correspondence_s=t1 - t0, depth_s=t2 - t1, correspondence_loss=float(floss),
                 depth_loss=float(fz), T_svd=T_svd)
    Xc = X @ T_svd[:3, :3].T + T_svd[:3, 3]
    if np.any(Xc[:, 2] <= 0):
        return tuple(sorted(pairs)), None, stats, "paper method: SVD pose puts fiducials behind the camera"
    pairs = sorted(pairs)
    ii = np.array([p[0] for p in pairs])
    mi = np.array([p[1] for p in pairs])
    ref = refine_pose(T_svd, X[mi], xn[ii], fxy, radius_mm)  # residuals in pair order
    return tuple(pairs), ref, stats, ""
