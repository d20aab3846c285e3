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
5. The best few hypotheses (by that cost) with *distinct* assignments are refined: gated
   one-to-one assignment (Hungarian), LM on all pairs, re-assignment with the tighter final
   gate, LM again. Refined candidates are ranked by the MSAC cost
   C = sum of squared residuals + final_gate^2 per unexplained image point: more pairs only
   win if they fit (ranking by pair count first let a 5-pair fit at 2.6 px RMS beat the true
   4-pair fit at 0.2 px with one stray; measured, hence this rule).
6. Stopping (deterministic): a solution with c pairs costs at least (m - c) gate^2, so only
   solutions with c >= k_need pairs could beat, or tie within the ambiguity margin, the best
   one. Every all-inlier image triplet re-finds its solution, so such a solution can only
   have escaped if a set of m - k_need image points hits every tried triplet; the search
   stops as soon as no such set exists (checked exhaustively), or the budget is spent.
   With m <= ``exhaustive_below`` image points every triplet is tried.
7. Ambiguity: the best different assignment (neither a subset nor a superset of the best
   one) is returned as runner-up; ``register`` refuses the result when :func:`is_ambiguous`
   says the runner-up explains the image about as well (known-noise cost margin, or an F-test
   on the residual variances for equal-size competitors).

Limits (measured in benchmarks/registration.py and the tests): with exactly 4 fiducials seen
a share of scenes is refused as ambiguous (4 points leave 2 residual dof; several 4-subsets of
9 fiducials can fit); with 4 strays among 9 image points at 1 px noise the truth can be missed
inside the 40-triplet budget (~2 % wrong in our runs; set ``sigma_floor_px`` to the detector's
noise to make the ambiguity test stricter).
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
    triplets_per_batch: int = 1
    refine_top: int = 3
    refine_top_exhaustive: int = 12
    #: Two assignments whose MSAC costs differ by less than ambiguity_k * sigma^2 (sigma the
    #: best fit's noise estimate, floored at sigma_floor_px) are called ambiguous: a likelihood
    #: ratio below exp(ambiguity_k / 2) ~ 90 is no basis for choosing.
    ambiguity_k: float = 9.0
    sigma_floor_px: float = 0.3
    accept_rms_px: float = 3.0
    #: With this many image points or fewer, every image triplet is tried (ambiguity safety).
    exhaustive_below: int = 5


@dataclass
class Candidate:
    pairs: tuple                # ((image_idx, model_idx), ...) sorted by image index
    refinement: Refinement
    rms_px: float
    found_by: set = field(default_factory=set)
    #: MSAC cost (px^2): sum of squared residuals + final_gate^2 per unexplained image point
    cost: float = float("inf")

    @property
    def count(self) -> int:
        return len(self.pairs)


@lru_cache(maxsize=32)
def _model_triplets(n: int) -> np.ndarray:
    return np.array(list(permutations(range(n), 3)), dtype=int).reshape(-1, 3)


def _sigma(c: "Candidate") -> float:
    r = c.refinement.residuals.ravel()
    dof = r.size - 6
    return float(np.sqrt(r @ r / dof)) if dof > 0 else 0.0


def ambiguity_margin(best: "Candidate", opts: RobustOptions) -> float:
    """Cost margin (px^2) under which a different assignment counts as equally good:
    ``ambiguity_k * sigma^2``, sigma the best fit's noise estimate floored at
    ``sigma_floor_px`` (the detector noise we assume)."""
    return opts.ambiguity_k * max(_sigma(best), opts.sigma_floor_px) ** 2


def is_ambiguous(best: "Candidate", runner: "Candidate | None", opts: RobustOptions) -> bool:
    """Whether ``runner`` (a different assignment) explains the image about as well as ``best``.

    Two tests, either suffices:

    * known-noise test: cost difference below :func:`ambiguity_margin`;
    * scale-free test, when the runner-up has at least as many pairs and both fits have >= 4
      residual dof: the variance ratio (S_r / dof_r) / (S_b / dof_b) is below the 95 % F
      quantile, i.e. the data cannot tell the two fits apart whatever the noise. This catches
      a lucky wrong fit that beats the truth at high noise (measured: 5 fiducials + 4 strays at
      1 px). With exactly 4 pairs (2 dof) only the known-noise test applies; set
      ``sigma_floor_px`` to the detector's noise.
    """
    if runner is None:
        return False
    if runner.cost - best.cost < ambiguity_margin(best, opts):
        return True
    db, dr = 2 * best.count - 6, 2 * runner.count - 6
    if runner.count >= best.count and db >= 4 and dr >= 4:
        from monotracker.registration.quantiles import f_ppf

        sb = float(np.sum(best.refinement.residuals**2)) / db
        sr = float(np.sum(runner.refinement.residuals**2)) / dr
        return sr < f_ppf(0.95, dr, db) * max(sb, 1e-12)
    return False


def _no_better_possible(k: int, m: int, tried: list) -> bool:
    """True when no solution with more than k inlier image points can have escaped the search.

    Any all-inlier image triplet re-finds the true solution. A better solution (>= k+1 inliers
    among m) escapes only if its m-k-1 (or fewer) outliers hit every tried triplet; we check
    exhaustively that no set of m-k-1 image points does (a deterministic stopping rule,
    cheaper and stricter than RANSAC's probabilistic one).
    """
    r = m - k - 1
    if r < 0:
        return True
    if r == 0:
        return len(tried) > 0
    sets = [set(t) for t in tried]
    for outl in combinations(range(m), r):
        o = set(outl)
        if all(s & o for s in sets):
            return False
    return True


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
    # Spread: first triplets disjoint from every one already chosen, then sharing at most one
    # point, then the rest (so one stray blob cannot spoil all early triplets, and the
    # hitting-set stopping rule is satisfied after few triplets).
    chosen: list[int] = []
    for limit in (0, 1):
        for i in order:
            if i in chosen:
                continue
            t = set(tris[i])
            if all(len(t & set(tris[j])) <= limit for j in chosen):
                chosen.append(i)
    first = chosen
    rest = [i for i in order if i not in set(chosen)]
    return [tuple(tris[i]) for i in first + rest]


def _score(R, t, X, xn, fxy, gate_px, radius_mm):
    """MSAC cost and inlier counts of S poses (R (S,3,3), t (S,3))."""
    Xc = R @ X.T + t[:, :, None]  # (S, 3, n)
    z = Xc[:, 2]
    s = z / (z * z - radius_mm * radius_mm) if radius_mm else 1.0 / z
    px = (Xc[:, 0] * s * fxy[0])[:, :, None]
    py = (Xc[:, 1] * s * fxy[1])[:, :, None]
    ox = xn[:, 0] * fxy[0]
    oy = xn[:, 1] * fxy[1]
    dx = px - ox
    dy = py - oy
    dmin = (dx * dx + dy * dy).min(axis=1)  # (S, m)
    g2 = gate_px * gate_px
    cost = np.minimum(dmin, g2).sum(axis=1)
    inl = (dmin < g2).sum(axis=1)
    in_front = z.min(axis=1) > (radius_mm or 0.0) + 1.0
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
        o = np.argsort(ii)
        mi, ii = mi[o], ii[o]  # residual order = pair order (sorted by image index)
        new_pairs = tuple(sorted(zip(ii.tolist(), mi.tolist())))
        if len(mi) < 4:
            return new_pairs, None
        if ref is not None and new_pairs == pairs:
            continue  # same assignment as the last refinement: nothing to redo
        ref = refine_pose(T, X[mi], xn[ii], fxy, radius_mm)
        T = ref.T
        pairs = new_pairs
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
    # Few image points: every triplet is tried anyway, so solve them all in one batch.
    per_batch = len(order) if m <= opts.exhaustive_below else opts.triplets_per_batch
    for b0 in range(0, len(order), max(per_batch, 1)):
        batch = order[b0: b0 + per_batch]
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
        idx = idx[np.argsort(cost[idx], kind="stable")]
        # refine the best few hypotheses (by rough MSAC cost) with distinct assignments
        done = 0
        seen_rough = set()
        top = opts.refine_top_exhaustive if per_batch == len(order) else opts.refine_top
        for h in idx:
            if done >= top:
                break
            T0 = np.eye(4)
            T0[:3, :3], T0[:3, 3] = R[h], t[h]
            pairs, ref = refine_assignment(T0, X, xn, fxy, radius_mm,
                                           (opts.hypothesis_gate_px, opts.final_gate_px))
            trip = batch[tri_of[src[h]]]
            if pairs in cands:
                cands[pairs].found_by.add(trip)
            if pairs in seen_rough:
                continue
            seen_rough.add(pairs)
            done += 1
            if ref is None or pairs in cands:
                continue
            r2 = float(np.sum(ref.residuals**2))
            cands[pairs] = Candidate(pairs, ref, float(np.sqrt(r2 / len(pairs))), {trip},
                                     cost=r2 + (m - len(pairs)) * opts.final_gate_px**2)
        if cands:
            best = min(cands.values(), key=lambda c: c.cost)
            if best.rms_px <= opts.accept_rms_px and m > opts.exhaustive_below:
                bound = best.cost + ambiguity_margin(best, opts)
                k_need = max(4, int(np.floor(m - bound / opts.final_gate_px**2)) + 1)
                if _no_better_possible(k_need - 1, m, order[:tried]):
                    break
    stats = {"image_triplets": tried, "hypotheses": hyps, "candidates": len(cands)}
    if not cands:
        return None, None, stats
    ranked = sorted(cands.values(), key=lambda c: c.cost)
    best = ranked[0]
    runner = None
    bp = set(best.pairs)
    for c in ranked[1:]:
        cp = set(c.pairs)
        if not (cp <= bp or bp <= cp):
            runner = c
            break
    return best, runner, stats
