"""2D KD-tree ordering of point sets (paper section 2.2.2), vectorised over batches.

The paper orders points "by the construction rule of a 2D KD-tree" without fixing the
details. Our choices:

* split on x at depth 0, y at depth 1, alternating;
* the median of a subset of k points (sorted by the split coordinate, ties broken by the other
  coordinate, then by index, so the order is deterministic) is element ``(k - 1) // 2`` (the
  lower median); the left subtree holds the smaller coordinates;
* points are read in *pre-order* (node, left subtree, right subtree), i.e. the order in which
  the construction creates the nodes.

Because the tree's shape depends only on n, a batch of point sets (B, n, 2) is ordered with a
fixed sequence of batched argsorts, with no per-set Python recursion (needed inside PSO).
"""

from __future__ import annotations

import numpy as np


def kd_order(P: np.ndarray) -> np.ndarray:
    """Indices (B, n) (or (n,) for a single set) reading P (B, n, 2) in KD pre-order."""
    P = np.asarray(P, dtype=float)
    single = P.ndim == 2
    if single:
        P = P[None]
    B, n, _ = P.shape
    idx = np.broadcast_to(np.arange(n), (B, n)).copy()
    out = _order(P, idx, 0)
    return out[0] if single else out


def _order(P: np.ndarray, idx: np.ndarray, depth: int) -> np.ndarray:
    k = idx.shape[1]
    if k <= 1:
        return idx
    ax = depth % 2
    coords = np.take_along_axis(P[:, :, ax], idx, axis=1)
    other = np.take_along_axis(P[:, :, 1 - ax], idx, axis=1)
    # lexsort: primary split coordinate, then the other coordinate, then index
    srt = _lexsort_rows(coords, other, idx)
    idx = np.take_along_axis(idx, srt, axis=1)
    mid = (k - 1) // 2
    left = _order(P, idx[:, :mid], depth + 1)
    right = _order(P, idx[:, mid + 1:], depth + 1)
    return np.concatenate([idx[:, mid:mid + 1], left, right], axis=1)


def _lexsort_rows(primary: np.ndarray, secondary: np.ndarray, tertiary: np.ndarray) -> np.ndarray:
    """Row-wise lexicographic argsort by (primary, secondary, tertiary)."""
    o = np.argsort(tertiary, axis=1, kind="stable")
    o = np.take_along_axis(o, np.argsort(np.take_along_axis(secondary, o, 1), axis=1, kind="stable"), 1)
    o = np.take_along_axis(o, np.argsort(np.take_along_axis(primary, o, 1), axis=1, kind="stable"), 1)
    return o
