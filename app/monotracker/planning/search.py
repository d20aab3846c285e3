"""The layout search for one camera pose: which candidates to use as balls.

Objective (what the planner minimises): the RMS error at the target with the worst single ball
hidden, ``max_i RMS(S minus i)`` (the margin for losing any one ball), for layouts of at least
``min_fiducials + 1`` balls; smaller layouts use the RMS with every ball seen. RMS comes from
the registration's covariance (:func:`~monotracker.registration.report.pose_covariance`,
:func:`~monotracker.registration.report.target_covariance`, on stacks of normal matrices),
at 1 px of noise: the noise scales every layout alike, so it does not change the choice. The
pose tracker's shading cover (:func:`.trust.shading_cover`) is left out of the ranking: its
per-ball floor scales every layout alike too, and its shift common to all balls is absorbed by
a translation parallel to the image, nearly the same for every layout from one camera pose
(the predictions of :mod:`.prediction` include both).

Search (an exchange algorithm, as for optimal experimental designs):

1. seed with the ``min_fiducials`` candidates spread farthest apart (farthest-point sampling);
2. add the candidate that lowers the objective most until there are ``n`` balls;
3. exchange passes: for each ball, the candidate that would serve best in its place takes it,
   until a pass changes nothing (at most ``max_passes``).

Every step honours the separation (``min_separation_mm`` between centres) and leaves ``keep``
balls (existing fiducials the user keeps) where they are. Deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monotracker.registration.report import pose_covariance, target_covariance

#: the largest stack of 6x6 normal matrices inverted at once (memory: ~100 MB of float64)
_CHUNK = 20000
#: smallest out-of-plane / in-plane spread ratios of a layout and of every layout less one ball:
#: twice the pose tracker's refusal limits (``vision.pose_checks.weak_geometry``)
MIN_DEPTH_RATIO = 0.06
MIN_WIDTH_RATIO = 0.2


@dataclass
class PoseData:
    """One camera pose's view of the candidates: ``T_cam_ct`` (4x4), ``info`` (n, 6, 6) each
    candidate's share of the normal matrix (zeros where it is not seen), ``seen`` (n,) bool,
    ``usable`` (n,) bool: seen and allowed as a new ball; ``target`` (3,) LPS mm."""

    T_cam_ct: np.ndarray
    info: np.ndarray
    seen: np.ndarray
    usable: np.ndarray
    target: np.ndarray


def rms2(pd: PoseData, M: np.ndarray) -> np.ndarray:
    """Squared RMS error at the target (mm^2 at 1 px) for normal matrices ``M`` (..., 6, 6)."""
    M = np.asarray(M, float)
    flat = M.reshape(-1, 6, 6)
    out = np.empty(len(flat))
    for s in range(0, len(flat), _CHUNK):
        cov3 = target_covariance(pd.T_cam_ct, pose_covariance(flat[s:s + _CHUNK], 1.0), pd.target)
        out[s:s + _CHUNK] = np.trace(cov3, axis1=-2, axis2=-1)
    return out.reshape(M.shape[:-2])


def too_flat(points: np.ndarray) -> np.ndarray:
    """(...,) bool: point sets (..., k, 3) mm whose principal spreads (s0 >= s1 >= s2) have
    ``s2 / s0 < MIN_DEPTH_RATIO`` or ``s1 / s0 < MIN_WIDTH_RATIO``: the pose tracker refuses
    near-coplanar or near-collinear matched balls (``vision.pose_checks.weak_geometry``, 0.03 and
    0.1), and a planar layout's pose is two-fold ambiguous; the planner keeps a margin."""
    P = np.asarray(points, float)
    s = np.linalg.svd(P - P.mean(axis=-2, keepdims=True), compute_uv=False)
    return (s[..., 2] < MIN_DEPTH_RATIO * s[..., 0]) | (s[..., 1] < MIN_WIDTH_RATIO * s[..., 0])


def objective(pd: PoseData, layouts: np.ndarray, min_fiducials: int = 4, points: np.ndarray | None = None) -> np.ndarray:
    """(B,) objective (mm^2 at 1 px; see the module docstring) of ``layouts`` (B, k) candidate
    indices; inf where a layout cannot give a pose (fewer than ``min_fiducials`` balls seen, or,
    with ``points`` (m, 3) the candidate centres, the seen balls or any of them less one
    :func:`too_flat`)."""
    L = np.asarray(layouts, int)
    B, k = L.shape
    A = pd.info[L]                                  # (B, k, 6, 6)
    seen = pd.seen[L]
    M = A.sum(axis=1)
    n_seen = seen.sum(axis=1)
    flat = np.zeros(B, bool)
    if points is not None and k >= min_fiducials:
        P = np.asarray(points, float)[L]            # (B, k, 3)
        flat = too_flat(P)
        if k > min_fiducials:
            drop = np.array([np.delete(np.arange(k), i) for i in range(k)])     # (k, k - 1)
            flat |= too_flat(P[:, drop]).any(axis=1)
    if k <= min_fiducials:
        out = rms2(pd, M)
        return np.where((n_seen >= min_fiducials) & ~flat, out, np.inf)
    worst = rms2(pd, M[:, None] - A).max(axis=1)    # each ball hidden in turn
    return np.where((n_seen - 1 >= min_fiducials) & ~flat, worst, np.inf)


def _far_enough(points: np.ndarray, idx: np.ndarray, chosen, min_sep: float) -> np.ndarray:
    """(len(idx),) bool: candidates ``idx`` lie at least ``min_sep`` (mm) from every ``chosen`` one."""
    chosen = np.asarray(chosen, int)
    if len(chosen) == 0:
        return np.ones(len(idx), bool)
    d = np.linalg.norm(points[idx][:, None, :] - points[chosen][None], axis=2)
    return np.all(d >= min_sep, axis=1)


def spread_seed(points: np.ndarray, pool: np.ndarray, k: int, min_sep: float,
                start: np.ndarray | None = None) -> list[int]:
    """``k`` indices from ``pool`` spread farthest apart (farthest-point sampling from the
    pool's centre outwards), after the ``start`` indices already chosen."""
    chosen = [int(i) for i in (start if start is not None else [])]
    pool = np.asarray(pool, int)
    while len(chosen) < k:
        ok = pool[_far_enough(points, pool, chosen, min_sep)]
        ok = ok[~np.isin(ok, chosen)]
        if len(ok) == 0:
            break
        if chosen:
            d = np.min(np.linalg.norm(points[ok][:, None] - points[chosen][None], axis=2), axis=1)
        else:
            d = np.linalg.norm(points[ok] - points[pool].mean(axis=0), axis=1)
        chosen.append(int(ok[np.argmax(d)]))
    return chosen


def best_layout(pd: PoseData, points: np.ndarray, n: int, min_sep: float, keep: tuple = (),
                min_fiducials: int = 4, max_passes: int = 4, exchange: bool = True) -> tuple[list[int], float]:
    """The search of the module docstring for one pose: (candidate indices, objective mm^2 at
    1 px). ``points`` (m, 3) candidate centres; ``keep`` indices that stay. Fewer than ``n``
    when the usable candidates run out."""
    keep = [int(i) for i in keep]
    pool = np.flatnonzero(pd.usable)
    pool = pool[~np.isin(pool, keep)]
    S = spread_seed(points, pool, min(min_fiducials, n), min_sep, np.array(keep, int))
    while len(S) < n:
        c = _best_addition(pd, points, S, pool, min_sep, min_fiducials)
        if c is None:
            break
        S.append(c)
    val = float(objective(pd, np.array([S]), min_fiducials, points)[0])
    if not exchange:
        return S, val
    for _ in range(max_passes):
        changed = False
        for pos in range(len(S)):
            if S[pos] in keep:
                continue
            rest = S[:pos] + S[pos + 1:]
            cand = pool[_far_enough(points, pool, rest, min_sep)]
            cand = cand[~np.isin(cand, rest)]
            if len(cand) == 0:
                continue
            L = np.array([rest[:pos] + [c] + rest[pos:] for c in cand])
            obj = objective(pd, L, min_fiducials, points)
            j = int(np.argmin(obj))
            if obj[j] < val * (1.0 - 1e-9) and cand[j] != S[pos]:
                S[pos] = int(cand[j])
                val = float(obj[j])
                changed = True
        if not changed:
            break
    return S, val


def _best_addition(pd, points, S, pool, min_sep, min_fiducials) -> int | None:
    cand = pool[_far_enough(points, pool, S, min_sep)]
    cand = cand[~np.isin(cand, S)]
    if len(cand) == 0:
        return None
    L = np.column_stack([np.repeat(np.array(S, int)[None], len(cand), axis=0), cand])
    obj = objective(pd, L, min_fiducials, points)
    if not np.any(np.isfinite(obj)):     # too few to judge yet: the farthest from the others
        return spread_seed(points, cand, len(S) + 1, min_sep, np.array(S, int))[-1]
    return int(cand[int(np.argmin(obj))])


def swap_map(pd: PoseData, points: np.ndarray, layout: list[int], min_sep: float, keep: tuple = (),
             min_fiducials: int = 4) -> np.ndarray:
    """(m,) objective (mm^2 at 1 px) of ``layout`` with one of its balls (not one of ``keep``)
    moved to each candidate, the best choice of which ball; NaN where a candidate is not
    usable or no ball may move there (separation). The layout's own positions get its value."""
    m = len(pd.usable)
    out = np.full(m, np.nan)
    S = [int(i) for i in layout]
    if not S:
        return out
    out[S] = float(objective(pd, np.array([S]), min_fiducials, points)[0])
    pool = np.flatnonzero(pd.usable)
    pool = pool[~np.isin(pool, S)]
    for pos in range(len(S)):
        if S[pos] in keep:
            continue
        rest = S[:pos] + S[pos + 1:]
        cand = pool[_far_enough(points, pool, rest, min_sep)]
        if len(cand) == 0:
            continue
        L = np.array([rest + [c] for c in cand])
        obj = objective(pd, L, min_fiducials, points)
        cur = out[cand]
        out[cand] = np.where(np.isnan(cur), obj, np.minimum(cur, obj))
    return out
