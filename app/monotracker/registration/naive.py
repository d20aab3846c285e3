"""``method="naive"``: a plain hypothesise-and-verify baseline for the benchmark.

Uniform random draws of (image triplet, ordered model triplet), one ``cv2.solveP3P`` call
each, verification of every returned pose in a Python loop (inlier count within the
hypothesis gate), fixed budget of ``NAIVE_BUDGET`` draws, best pose refined once with the
common assignment + LM. No pruning, no batching, no stopping rule, no ambiguity check: this
is what the robust method's design is measured against.
"""

from __future__ import annotations

import cv2
import numpy as np

from .projection import project_normalised
from .robust import refine_assignment

NAIVE_BUDGET = 3000


def naive_search(X, xn, K, fxy, radius_mm, opts, rng_seed: int = 0):
    rng = np.random.default_rng(rng_seed)
    n, m = len(X), len(xn)
    I3 = np.eye(3)
    obs = xn * fxy
    best = (-1, np.inf, None)
    for _ in range(NAIVE_BUDGET):
        ii = rng.choice(m, 3, replace=False)
        mi = rng.choice(n, 3, replace=False)
        try:
            k, rvecs, tvecs = cv2.solveP3P(X[mi].astype(np.float64), xn[ii].astype(np.float64).reshape(-1, 1, 2),
                                           I3, None, flags=cv2.SOLVEPNP_P3P)
        except cv2.error:
            continue
        for rv, tv in zip(rvecs, tvecs):
            R, _ = cv2.Rodrigues(rv)
            Xc = X @ R.T + tv.ravel()
            if np.any(Xc[:, 2] <= 0):
                continue
            p = project_normalised(Xc, radius_mm) * fxy
            d = np.sqrt(np.min(np.sum((p[:, None] - obs[None]) ** 2, axis=2), axis=0))
            inl = int(np.sum(d < opts.hypothesis_gate_px))
            cost = float(np.sum(np.minimum(d, opts.hypothesis_gate_px) ** 2))
            if inl > best[0] or (inl == best[0] and cost < best[1]):
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = R, tv.ravel()
                best = (inl, cost, T)
    if best[2] is None:
        return (), None, {"hypotheses": NAIVE_BUDGET}
    pairs, ref = refine_assignment(best[2], X, xn, fxy, radius_mm, (opts.hypothesis_gate_px, opts.final_gate_px))
    return pairs, ref, {"hypotheses": NAIVE_BUDGET}
