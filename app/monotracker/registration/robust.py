"""``method="robust"``: correspondence-free registration by hypothesise-and-verify.

1. Image triplets (3 of the m undistorted image points) are tried in an order that favours
   large, well-shaped triangles and spreads over different points (so one stray blob cannot
   spoil every early triplet). Triangles with an angle below 8 deg are skipped (ill-posed P3P).
2. Each image triplet is paired with *every ordered* model triplet (n(n-1)(n-2) of them), pruned
   by a perspective bound: two points seen under an angle theta at a distance of at least
   ``min_depth_mm`` from the camera are at least ``min_depth_mm * sin(theta)`` apart.
3. All surviving pairs go through the batched P3P solver (:mod:`.p3p`); poses that put the
   model centroid outside [min_depth_mm, max_depth_mm] or any fiducial behind the camera
   are dropped.
4. Verification projects all n model points with every pose and scores it MSAC-style against
   all m image points: cost = sum over image points of min(d^2, gate^2), d the distance in
   equivalent px to the nearest projected fiducial (strays and missing fiducials cost a
   constant). Inliers = image points within the gate.
5. The best few hypotheses with *distinct* assignments are refined: gated one-to-one
   assignment (Hungarian), LM on all pairs, re-assignment with a tighter gate, LM again.
6. Search stops when a refined solution explains every image point or every fiducial, or
   when the same assignment has been found from two different image triplets (an all-inlier
   triplet always re-finds the truth), or when the triplet budget is spent.
7. Ambiguity: if a second, different assignment with at least as many pairs fits within the
   acceptance gate and its RMS is within ``ambiguity_ratio`` of the best, the result is refused.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from itertools import combinations, permutations

import numpy as np

from .assign import gated_assignment
from .p3p import p3p_batch
from .pnp import Refinement, refine_pose
from .projection import bearings, project_normalised


@dataclass
class RobustOptions:
    """Tunables of the robust search (px are equivalent pinhole pixels, depths in mm)."""

    min_depth_mm: float = 200.0
    max_depth_mm: float = 1500.0
    hypothesis_gate_px: float = 10.0
    final_gate_px: float = 5.0
    max_image_triplets: int = 40
    triplets_per_batch: int = 2
    refine_top: int = 3
    ambiguity_ratio: float = 2.0
    accept_rms_px: float = 3.0
    miss_probability: float = 0.01


@dataclass
class Candidate:
    pairs: tuple                # ((image_idx, model_idx), ...) sorted by image index
    refinement: Refinement
    rms_px: float
    found_by: set = field(default_factory=set)

    @property
    def count(self) -> int:
        return len(self.pairs)


@lru_cache(maxsize=32)
def _model_triplets(n: int) -> np.ndarray:
    return np.array(list(permutations(range(n), 3)), dtype=int).reshape(-1, 3)


def _miss_probability(k: int, m: int, tried: int) -> float:
    """Chance that ``tried`` random image triplets all missed a solution with k inlier points
    among m (each triplet is all-inlier with probability C(k,3) / C(m,3)). Our triplet order
    spreads over points, so the real chance is lower: this is a conservative stopping rule."""
    from math import comb

    if k > m:
        return 0.0
    p = comb(k, 3) / comb(m, 3)
    return (1.0 - p) ** tried


def _image_triplet_order(xn: np.ndarray) -> list[tuple[int, int, int]]:
    m = len(xn)
    tris = np.array(list(combinations(range(m), 3)), dtype=int)
    if len(tris) == 0:
        return []
    P = xn[tris]
    a = np.linalg.norm(P[:, 1] - P[:, 2], axis=1)
    b = np.linalg.norm(P[:, 0] - P[:, 2], axis=1)
    c = np.linalg.norm(P[:, 0] - P[:, 1], axis=1)
    e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    # smallest angle via the law of sines on the shortest side
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.sort(np.stack([a, b, c], 1), axis=1)
        min_angle = np.degrees(np.arcsin(np.clip(2 * area / (s[:, 1] * s[:, 2]), 0, 1)))
    ok = min_angle > 8.0
    score = np.where(ok, area * np.minimum(min_angle, 30.0), -1.0)
    order = np.argsort(-score)
    order = [i for i in order if ok[i]]
    # Spread: first take triplets sharing at most one point with each already chosen one.
    first, rest = [], []
    for i in order:
        t = set(tris[i])
        if all(len(t & set(tris[j])) <= 1 for j in first):
            first.append(i)
        else:
            rest.append(i)
    return [tuple(tris[i]) for i in first + rest]


def _score(R, t, X, xn, fxy, gate_px, radius_mm):
    """MSAC cost and inlier counts of S poses (R (S,3,3), t (S,3))."""
    Xc = np.einsum("sij,kj->ski", R, X) + t[:, None, :]
    proj = project_normalised(Xc, radius_mm) * fxy
    obs = xn * fxy
    d2 = np.sum((proj[:, :, None, :] - obs[None, None, :, :]) ** 2, axis=3)  # (S, n, m)
    dmin = d2.min(axis=1)  # (S, m)
    g2 = gate_px * gate_px
    cost = np.minimum(dmin, g2).sum(axis=1)
    inl = (dmin < g2).sum(axis=1)
    in_front = Xc[:, :, 2].min(axis=1) > (radius_mm or 0.0) + 1.0
    cost = np.where(in_front, cost, np.inf)
    return cost, inl


def refine_assignment(T0, X, xn, fxy, radius_mm, gates) -> tuple[tuple, Refinement | None]:
    """Assign with each gate in turn and refine; returns (pairs, refinement)."""
    T = T0
    ref = None
    pairs = ()
    obs_px = xn * fxy
    for gate in gates:
        Xc = X @ T[:3, :3].T + T[:3, 3]
        if np.any(Xc[:, 2] <= 0):
            return (), None
        pred = project_normalised(Xc, radius_mm) * fxy
        mi, ii = gated_assignment(pred, obs_px, gate)
        if len(mi) < 4:
            return tuple(sorted(zip(ii.tolist(), mi.tolist()))), None
        ref = refine_pose(T, X[mi], xn[ii], fxy, radius_mm)
        T = ref.T
        pairs = tuple(sorted(zip(ii.tolist(), mi.tolist())))
    return pairs, ref


def robust_search(X: np.ndarray, xn: np.ndarray, fxy: np.ndarray, radius_mm: float | None,
                  opts: RobustOptions | None = None) -> tuple[Candidate | None, Candidate | None, dict]:
    """Run the search. Returns (best, runner_up, stats); candidates are refined."""
    opts = opts or RobustOptions()
    n, m = len(X), len(xn)
    f_img = bearings(xn)
    mtri = _model_triplets(n)
    Xt = X[mtri]  # (T, 3, 3)
    dX = np.stack([np.linalg.norm(Xt[:, 1] - Xt[:, 2], axis=1), np.linalg.norm(Xt[:, 0] - Xt[:, 2], axis=1),
                   np.linalg.norm(Xt[:, 0] - Xt[:, 1], axis=1)], axis=1)
    full = min(n, m)
    cands: dict[tuple, Candidate] = {}
    tried = 0
    hyps = 0
    order = _image_triplet_order(xn)[: opts.max_image_triplets]
    best = None
    for b0 in range(0, len(order), opts.triplets_per_batch):
        batch = order[b0: b0 + opts.triplets_per_batch]
        fs, Xs, src_tri = [], [], []
        for k, tri in enumerate(batch):
            F = f_img[list(tri)]
            cosang = np.array([F[1] @ F[2], F[0] @ F[2], F[0] @ F[1]])
            sin_th = np.sqrt(np.clip(1 - cosang**2, 0, 1))
            keep = np.all(dX >= opts.min_depth_mm * sin_th * 0.98, axis=1)
            idx = np.nonzero(keep)[0]
            fs.append(np.broadcast_to(F, (len(idx), 3, 3)))
            Xs.append(Xt[idx])
            src_tri.append(np.full(len(idx), k))
        f_all = np.concatenate(fs)
        X_all = np.concatenate(Xs)
        tri_of = np.concatenate(src_tri)
        hyps += len(f_all)
        tried += len(batch)
        R, t, src = p3p_batch(f_all, X_all)
        if len(src) == 0:
            continue
        zc = (R @ X.mean(axis=0)) [:, 2] + t[:, 2]
        okd = (zc > opts.min_depth_mm) & (zc < opts.max_depth_mm)
        R, t, src = R[okd], t[okd], src[okd]
        if len(src) == 0:
            continue
        cost, inl = _score(R, t, X, xn, fxy, opts.hypothesis_gate_px, radius_mm)
        finite = np.isfinite(cost) & (inl >= min(4, full))
        if not finite.any():
            continue
        idx = np.nonzero(finite)[0]
        idx = idx[np.lexsort((cost[idx], -inl[idx]))]
        # refine the best few distinct hypotheses of this batch
        done = 0
        seen_rough = set()
        for h in idx:
            if done >= opts.refine_top:
                break
            T0 = np.eye(4)
            T0[:3, :3], T0[:3, 3] = R[h], t[h]
            pairs, ref = refine_assignment(T0, X, xn, fxy, radius_mm,
                                           (opts.hypothesis_gate_px, opts.final_gate_px, opts.final_gate_px))
            if pairs in seen_rough:
                # same assignment again from this batch: still record which triplet found it
                if pairs in cands:
                    cands[pairs].found_by.add(batch[tri_of[src[h]]])
                continue
            seen_rough.add(pairs)
            done += 1
            if ref is None:
                continue
            rms = float(np.sqrt(np.mean(np.sum(ref.residuals**2, axis=1))))
            if pairs in cands:
                cands[pairs].found_by.add(batch[tri_of[src[h]]])
            else:
                cands[pairs] = Candidate(pairs, ref, rms, {batch[tri_of[src[h]]]})
        if cands:
            best = max(cands.values(), key=lambda c: (c.count, -c.rms_px))
            if best.rms_px <= opts.accept_rms_px and (
                    best.count >= full or (len(best.found_by) >= 2 and _miss_probability(best.count + 1, m, tried) < opts.miss_probability)):
                break
    stats = {"image_triplets": tried, "hypotheses": hyps, "candidates": len(cands)}
    if not cands:
        return None, None, stats
    ranked = sorted(cands.values(), key=lambda c: (-c.count, c.rms_px))
    best = ranked[0]
    runner = None
    for c in ranked[1:]:
        if set(c.pairs) != set(best.pairs) and not set(c.pairs) < set(best.pairs):
            runner = c
            break
    return best, runner, stats
