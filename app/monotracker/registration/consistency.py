"""Moved-fiducial detection: leave-one-out consistency of a registration.

A ball that shifted on the skin since the CT (or was re-stuck) still looks like a ball; a
registration that averages it in is wrong everywhere, and its FRE says little (FRE does not
predict TRE). Each fit is therefore checked one fiducial at a time:

1. **Leave one out.** For every matched fiducial i (at least ``MIN_PAIRS_LOO`` = 5 pairs, so
   that the other >= 4 determine the pose with redundancy), the pose is re-fitted without i
   (LM from the full fit) and i is predicted. Its prediction error e_i (px) has covariance
   ``S_i = sigma^2 (I + J_i C_-i J_i^T)``, C_-i = (J_-i^T J_-i)^-1 the pose covariance of the
   others and J_i i's projection Jacobian; ``d_i^2 = e_i^T S_i^-1 e_i`` is chi-square with 2
   dof when nothing moved (sigma known). sigma is the noise given by the caller (the stream's
   pooled estimate) unless the leave-one-out fit's own residual estimate (which the tested ball
   cannot inflate) is significantly larger; without a pooled value, the fit's own.
2. **Moved** = ``d_i^2`` over ``2 F_{1-p}(2, dof)`` (p = 1e-4 per fiducial; ``dof`` those of
   the noise estimate used, so that a sigma from few residuals does not raise false alarms;
   ~18.4, the chi-square quantile, once many frames are pooled) **and** the implied shift
   ``|e_i| * z_i / f`` (mm, perpendicular to the line of sight at the ball's depth) above
   ``min_shift_mm`` (1.0 mm). The second rule is the false-alarm guard: a detector bias of a few
   tenths of a pixel (a ball on the head's outline) is statistically visible but clinically
   irrelevant and must not make the system discard a good ball. A shift along the line of sight
   is invisible to one camera (and moves the pose little).
3. The worst offender is excluded and the pose re-solved without it (``register`` with the
   leave-one-out pose as prior); repeated up to ``max_exclusions`` times.
4. **Near miss.** A ball displaced by more than the registration's inlier gate (~2 mm at
   0.5 m) is not matched at all; it is named moved when an unmatched detection lies within
   ``max_shift_mm`` of its predicted position and passes the same test. (A stray blob next to
   a hidden ball looks the same; the consequence is only that the ball stays excluded.)

Index conventions as :func:`register`: pairs are (image index, fiducial index) into the
caller's full fiducial array; ``excluded`` fiducials are never used.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .api import register
from .pnp import _residuals_and_jacobian, refine_pose
from .quantiles import f_ppf
from .projection import undistort_to_normalised
from .result import Registration

#: false-alarm probability per fiducial and registration of the moved test
P_MOVED = 1e-4
MIN_PAIRS_LOO = 5


@dataclass(frozen=True)
class MovedFiducial:
    """A fiducial whose image disagrees with the others: ``fiducial_index`` (into the caller's
    CT array), ``image_index`` (the detection), ``shift_mm`` (estimated displacement across the
    line of sight, mm), ``error_px`` (leave-one-out prediction error, px), ``d2`` (its
    Mahalanobis square), ``how`` "leave-one-out" or "near-miss"."""

    fiducial_index: int
    image_index: int
    shift_mm: float
    error_px: float
    d2: float
    how: str
    T_without: np.ndarray | None = None
    #: degrees of freedom of the noise estimate behind ``d2`` (the gate is an F quantile)
    dof: int = 0


@dataclass
class Screened:
    """``registration`` the final result (indices into the full fiducial array; excluded
    fiducials appear in ``unmatched_fiducial_indices``); ``moved`` the fiducials found moved in
    this call; ``excluded`` all fiducials left out (given + found)."""

    registration: Registration
    moved: list = field(default_factory=list)
    excluded: list = field(default_factory=list)
    #: residual sum of squares (px^2) and dof for a noise pool: the final fit's, without its
    #: worst pair when that pair is suspect at the 1 % level (a ball that moved a little, not
    #: enough to be named, must not inflate the pooled noise); (nan, 0) without a fit
    noise_rss_px2: float = float("nan")
    noise_dof: int = 0
    #: wall time (s) of the first registration (``register``) and of the screening after it
    #: (leave-one-out tests, re-solves, near misses, noise sample)
    register_s: float = 0.0
    screen_s: float = 0.0


def _pick_sigma(s_loo: float, dof_loo: int, sigma_px: float | None, sigma_dof: int) -> tuple[float, int]:
    """(sigma px, its dof): the caller's pooled estimate unless this fit's own (leave-one-out)
    estimate is significantly larger (F-test, 1 %): then the noise rose now and the fit's own
    value, with its few dof, is used. Without a pooled estimate, the fit's own."""
    if sigma_px is not None and sigma_dof > 0 and np.isfinite(sigma_px) and sigma_px > 0:
        if dof_loo <= 0 or s_loo**2 / sigma_px**2 <= f_ppf(0.99, dof_loo, sigma_dof):
            return max(float(sigma_px), 1e-3), int(sigma_dof)
    return max(float(s_loo), 1e-3), int(max(dof_loo, 1))


def moved_gate(dof: int, p: float = P_MOVED) -> float:
    """Threshold on d2 for a 2D prediction error whose noise sigma was estimated with ``dof``
    degrees of freedom: ``2 F_{1-p}(2, dof)`` (-> the chi-square quantile for large dof).
    Using the chi-square quantile with a noise estimate from 10 dof raised false alarms ~50x."""
    return float(2.0 * f_ppf(1.0 - p, 2, max(int(dof), 1)))


def _deletion_quads(r: np.ndarray, J: np.ndarray, C: np.ndarray):
    """Per pair q of a fit with residuals r (2k,) px, Jacobian J (2k, 6) and C = (J^T J)^-1: the
    left-out prediction error ``e_q = (I - H_qq)^-1 r_q`` (k, 2) px and ``r_q^T e_q`` (k,), the
    drop in RSS without the pair; H_qq the 2x2 block of the hat matrix. All pairs at once; a
    singular block (only then, pair by pair) gives ``e_q = r_q * inf`` as before."""
    k = len(r) // 2
    Jq = J.reshape(k, 2, 6)
    rq = r.reshape(k, 2)
    IH = np.eye(2)[None] - np.einsum("qai,ij,qbj->qab", Jq, C, Jq)
    try:
        e = np.linalg.solve(IH, rq[..., None])[..., 0]
    except np.linalg.LinAlgError:
        e = np.empty((k, 2))
        for q in range(k):
            try:
                e[q] = np.linalg.solve(IH[q], rq[q])
            except np.linalg.LinAlgError:
                e[q] = rq[q] * np.inf
    return e, np.einsum("qa,qa->q", rq, e)


def _loo_one(T, X, obs, fxy, radius, i, sigma_px, sigma_dof=0):
    """Leave pair i out: (error px (2,), d2, T_without, dof of the sigma used)."""
    keep = np.arange(len(X)) != i
    ref = refine_pose(T, X[keep], obs[keep], fxy, radius, max_iter=10)
    Tw = ref.T
    k = int(keep.sum())
    dof = 2 * k - 6
    s_loo = float(np.sqrt(np.sum(ref.residuals**2) / dof)) if dof > 0 else 0.0
    sigma, sdof = _pick_sigma(s_loo, dof, sigma_px, sigma_dof)
    r_i, J_i = _residuals_and_jacobian(Tw[:3, :3], Tw[:3, 3], X[i:i + 1], obs[i:i + 1], fxy, radius)
    try:
        C = np.linalg.inv(ref.JtJ)
    except np.linalg.LinAlgError:
        return r_i, np.inf, Tw, sdof
    S = sigma**2 * (np.eye(2) + J_i @ C @ J_i.T)
    try:
        d2 = float(r_i @ np.linalg.solve(S, r_i))
    except np.linalg.LinAlgError:
        d2 = np.inf
    return r_i, d2, Tw, sdof


def _shift_mm(T, x_ct, err_px, fxy) -> float:
    z = float((T[:3, :3] @ x_ct + T[:3, 3])[2])
    return float(np.linalg.norm(np.asarray(err_px) / fxy) * z)


def leave_one_out(T: np.ndarray, X: np.ndarray, xn: np.ndarray, fxy: np.ndarray, radius_mm: float | None,
                  pairs, sigma_px: float | None = None, screen: bool = True,
                  sigma_dof: int = 0) -> list[MovedFiducial]:
    """Leave-one-out test of every pair; one :class:`MovedFiducial` record per pair (not yet
    judged), fiducial indices into ``X``.

    Screening is closed-form at the fit (the deletion formulas of least squares: the left-out
    prediction error is ``(I - H_ii)^-1 r_i`` with covariance ``sigma^2 (I - H_ii)^-1``, H the
    2x2 block of the hat matrix), which costs one Jacobian; pairs whose screened ``d2`` exceeds
    a quarter of their gate (all pairs when ``screen`` is False) are re-fitted without them
    exactly (LM), which also gives the pose without them. ``sigma_px`` / ``sigma_dof``: a noise
    estimate known from elsewhere (the stream's pool) and its dof."""
    pairs = list(pairs)
    k = len(pairs)
    if k < MIN_PAIRS_LOO:
        return []
    ii = np.array([p[0] for p in pairs])
    mi = np.array([p[1] for p in pairs])
    Xm, obs = X[mi], xn[ii]
    r, J = _residuals_and_jacobian(T[:3, :3], T[:3, 3], Xm, obs, fxy, radius_mm)
    try:
        C = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return []
    rss = float(r @ r)
    dof_loo = 2 * (k - 1) - 6
    out = []
    es, quads = _deletion_quads(r, J, C)
    for q in range(k):
        e = es[q]
        quad = float(quads[q])                     # r^T (I - H)^-1 r = drop in RSS
        s_loo = np.sqrt(max(rss - quad, 0.0) / dof_loo) if dof_loo > 0 else 0.0
        sigma, sdof = _pick_sigma(s_loo, dof_loo, sigma_px, sigma_dof)
        d2 = quad / sigma**2
        rec = MovedFiducial(int(mi[q]), int(ii[q]), _shift_mm(T, Xm[q], e, fxy), float(np.linalg.norm(e)),
                            float(d2), "leave-one-out", None, sdof)
        if not screen or d2 > moved_gate(sdof) / 4:
            e2, d2x, Tw, sdof2 = _loo_one(T, Xm, obs, fxy, radius_mm, q, sigma_px, sigma_dof)
            rec = MovedFiducial(int(mi[q]), int(ii[q]), _shift_mm(Tw, Xm[q], e2, fxy),
                                float(np.linalg.norm(e2)), float(d2x), "leave-one-out", Tw, sdof2)
        out.append(rec)
    return out


def noise_sample(T: np.ndarray, X: np.ndarray, xn: np.ndarray, fxy: np.ndarray, radius_mm: float | None,
                 pairs, p_suspect: float = 0.01) -> tuple[float, int]:
    """(RSS px^2, dof) of the fit for a noise pool, leaving out the worst pair when its
    leave-one-out test (own noise estimate, F quantile) is significant at ``p_suspect``. Under
    pure noise that trims ~k p_suspect of the frames, a small low bias (a few % in sigma)."""
    pairs = list(pairs)
    k = len(pairs)
    if k < 4:
        return float("nan"), 0
    ii = np.array([p[0] for p in pairs])
    mi = np.array([p[1] for p in pairs])
    r, J = _residuals_and_jacobian(T[:3, :3], T[:3, 3], X[mi], xn[ii], fxy, radius_mm)
    rss, dof = float(r @ r), 2 * k - 6
    if k < MIN_PAIRS_LOO:
        return rss, dof
    try:
        C = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return rss, dof
    _, quads = _deletion_quads(r, J, C)
    quads = np.where(np.isfinite(quads), quads, 0.0)   # a singular block counts as no drop, as before
    q = int(np.argmax(quads))
    dof_loo = dof - 2
    rest = max(rss - quads[q], 0.0)
    if dof_loo > 0 and rest > 0 and quads[q] / (rest / dof_loo) > moved_gate(dof_loo, p_suspect):
        return rest, dof_loo
    return rss, dof


def near_misses(T: np.ndarray, X: np.ndarray, xn: np.ndarray, fxy: np.ndarray, radius_mm: float | None,
                pairs, candidates, sigma_px: float, max_shift_mm: float, sigma_dof: int = 1) -> list[MovedFiducial]:
    """Unmatched fiducials (``candidates``, indices into X) with an unmatched detection within
    ``max_shift_mm`` of their predicted position under the pose ``T`` fitted to ``pairs``."""
    from .projection import project_normalised

    used_img = {p[0] for p in pairs}
    free = np.array([i for i in range(len(xn)) if i not in used_img], int)
    if len(free) == 0 or len(pairs) < 4:
        return []
    ii = np.array([p[0] for p in pairs])
    mi = np.array([p[1] for p in pairs])
    _, J = _residuals_and_jacobian(T[:3, :3], T[:3, 3], X[mi], xn[ii], fxy, radius_mm)
    try:
        C = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return []
    out = []
    for j in candidates:
        Xc = T[:3, :3] @ X[j] + T[:3, 3]
        if Xc[2] <= (radius_mm or 0.0):
            continue
        pred = project_normalised(Xc[None], radius_mm)[0]
        d = np.linalg.norm((xn[free] - pred) * fxy, axis=1)
        a = int(np.argmin(d))
        e = (xn[free[a]] - pred) * fxy
        shift = float(np.linalg.norm(e / fxy) * Xc[2])
        if shift > max_shift_mm:
            continue
        _, J_j = _residuals_and_jacobian(T[:3, :3], T[:3, 3], X[j:j + 1], xn[free[a]:free[a] + 1], fxy, radius_mm)
        S = sigma_px**2 * (np.eye(2) + J_j @ C @ J_j.T)
        out.append(MovedFiducial(int(j), int(free[a]), shift, float(np.linalg.norm(e)),
                                 float(e @ np.linalg.solve(S, e)), "near-miss", T, int(sigma_dof)))
    return out


def _remap(reg: Registration, active: np.ndarray, n_all: int, excluded) -> Registration:
    """Fiducial indices of a registration on ``X[active]`` -> indices into the full array."""
    reg.pairs = [(int(i), int(active[j])) for i, j in reg.pairs]
    if "rejected_pairs" in reg.stats:
        reg.stats["rejected_pairs"] = [(int(i), int(active[j])) for i, j in reg.stats["rejected_pairs"]]
    if "ambiguous_pairs" in reg.stats:
        reg.stats["ambiguous_pairs"] = [(int(i), int(active[j])) for i, j in reg.stats["ambiguous_pairs"]]
    matched = {j for _, j in reg.pairs}
    reg.unmatched_fiducial_indices = sorted(set(range(n_all)) - matched)
    reg.stats["excluded_fiducials"] = sorted(int(j) for j in excluded)
    return reg


def register_screened(fiducials_ct, image_points, K, dist=None, radius_mm=None, *, excluded=(), prior=None,
                      method: str = "robust", sigma_px: float | None = None, sigma_dof: int = 0,
                      min_shift_mm: float = 1.0, max_shift_mm: float = 8.0, p_false: float = P_MOVED,
                      max_exclusions: int = 2) -> Screened:
    """:func:`register` without the ``excluded`` fiducials, then the moved-fiducial test (module
    docstring); a moved fiducial is excluded and the pose re-solved. ``sigma_px``: the image
    noise known from earlier frames (px), or None (the fit's own leave-one-out estimate)."""
    X_all = np.asarray(fiducials_ct, float).reshape(-1, 3)
    pts = np.asarray(image_points, float).reshape(-1, 2)
    n = len(X_all)
    excl = set(int(j) for j in excluded)
    K = np.asarray(K, float)
    fxy = np.array([K[0, 0], K[1, 1]])
    radius = float(radius_mm) if radius_mm else None
    moved: list[MovedFiducial] = []

    def solve(prior_T):
        active = np.array([j for j in range(n) if j not in excl], int)
        r = register(X_all[active], pts, K, dist, radius_mm=radius_mm, method=method, prior=prior_T)
        return _remap(r, active, n, excl)

    t0 = time.perf_counter()
    reg = solve(prior)
    t_reg = time.perf_counter() - t0
    if len(pts) == 0 or not np.all(np.isfinite(pts)):
        return Screened(reg, moved, sorted(excl), register_s=t_reg, screen_s=time.perf_counter() - t0 - t_reg)
    xn = undistort_to_normalised(pts, K, dist)
    for _ in range(max_exclusions + 1):
        if reg.ok:
            T, pairs = reg.T_cam_ct, reg.pairs
        elif reg.stats.get("rejected_T_cam_ct") is not None and "ambiguous" not in reg.reason:
            T, pairs = reg.stats["rejected_T_cam_ct"], reg.stats.get("rejected_pairs", [])
        else:
            break
        if len(moved) >= max_exclusions:
            break
        tests = leave_one_out(T, X_all, xn, fxy, radius, pairs, sigma_px, sigma_dof=sigma_dof)
        bad = [m for m in tests if m.d2 > moved_gate(m.dof, p_false) and m.shift_mm > min_shift_mm
               and m.T_without is not None]
        if not bad:
            break
        worst = max(bad, key=lambda m: m.d2)
        moved.append(worst)
        excl.add(worst.fiducial_index)
        reg = solve(worst.T_without)
    if reg.ok and len(moved) < max_exclusions:
        unmatched = [j for j in reg.unmatched_fiducial_indices if j not in excl]
        own = reg.sigma_px if np.isfinite(reg.sigma_px) else 0.0
        sig, sdof = _pick_sigma(own, reg.sigma_dof, sigma_px, sigma_dof)
        for m in near_misses(reg.T_cam_ct, X_all, xn, fxy, radius, reg.pairs, unmatched, sig, max_shift_mm, sdof):
            if m.d2 > moved_gate(m.dof, p_false) and m.shift_mm > min_shift_mm and len(moved) < max_exclusions:
                moved.append(m)
                excl.add(m.fiducial_index)
        reg.stats["excluded_fiducials"] = sorted(excl)
    rss, dof = (noise_sample(reg.T_cam_ct, X_all, xn, fxy, radius, reg.pairs) if reg.ok
                else (float("nan"), 0))
    return Screened(reg, moved, sorted(excl), rss, dof, t_reg, time.perf_counter() - t0 - t_reg)
