"""``register()``: the public entry point (input checks, dispatch, acceptance, report)."""

from __future__ import annotations

import time

import numpy as np

from monotracker.errors import InputError

from .projection import undistort_to_normalised
from .report import fre_mm, pose_covariance, sigma_from_residuals
from .result import Registration
from .robust import RobustOptions, is_ambiguous, robust_search

METHODS = ("robust", "paper", "naive")

#: Acceptance gates (equivalent px): RMS of the final fit and the largest single residual.
ACCEPT_RMS_PX = 3.0
ACCEPT_MAX_PX = 6.0
#: Image points closer than this (px) are called duplicates; fiducials closer than
#: ``DUPLICATE_MM`` likewise.
DUPLICATE_PX = 1.0
DUPLICATE_MM = 1.0
#: A fiducial set whose out-of-plane spread (smallest / largest principal std) is below this
#: is called coplanar: correspondence-free matching of planar sets admits projectively
#: equivalent wrong assignments and a two-fold pose ambiguity, so we refuse rather than guess.
COPLANAR_RATIO = 0.03


def _fail(method: str, reason: str, t0: float, timing: dict | None = None, **kw) -> Registration:
    timing = dict(timing or {})
    timing["total_s"] = time.perf_counter() - t0
    return Registration(ok=False, reason=reason, method=method, timing=timing, **kw)


def _check_inputs(fiducials_ct, image_points, K, dist, radius_mm, prior):
    """Returns (X, pts, K, dist, prior, reason); reason non-empty on bad data."""
    try:
        X = np.asarray(fiducials_ct, dtype=float)
        pts = np.asarray(image_points, dtype=float)
        K = np.asarray(K, dtype=float)
    except (TypeError, ValueError):
        return None, None, None, None, None, "inputs are not numeric arrays"
    if X.ndim != 2 or X.shape[1] != 3:
        return None, None, None, None, None, f"fiducials_ct must be (n, 3) mm, got shape {X.shape}"
    if pts.size == 0:
        pts = pts.reshape(0, 2)
    if pts.ndim != 2 or pts.shape[1] != 2:
        return None, None, None, None, None, f"image_points must be (m, 2) px, got shape {pts.shape}"
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        return None, None, None, None, None, "K must be a finite 3x3 intrinsic matrix with positive focal lengths"
    if dist is not None:
        try:
            dist = np.asarray(dist, dtype=float).ravel()
        except (TypeError, ValueError):
            return None, None, None, None, None, "dist is not numeric"
        if dist.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
            return None, None, None, None, None, "dist must hold 4, 5, 8, 12 or 14 finite OpenCV coefficients"
    if radius_mm is not None:
        try:
            radius_mm = float(radius_mm)
        except (TypeError, ValueError):
            radius_mm = float("nan")
    if radius_mm is not None and not (np.isfinite(radius_mm) and radius_mm > 0):
        return None, None, None, None, None, "radius_mm must be a positive number of mm or None"
    if prior is not None:
        prior = np.asarray(prior, dtype=float)
        if prior.shape != (4, 4) or not np.all(np.isfinite(prior)):
            prior = None  # a broken prior is ignored: the full search does not need it
    if not np.all(np.isfinite(X)):
        return None, None, None, None, None, "fiducials_ct contains NaN or infinite values"
    if not np.all(np.isfinite(pts)):
        return None, None, None, None, None, "image_points contain NaN or infinite values"
    if len(X) < 4:
        return None, None, None, None, None, f"only {len(X)} CT fiducials; need at least 4"
    if len(pts) < 4:
        return None, None, None, None, None, f"only {len(pts)} image points; need at least 4 fiducials in view"
    dX = np.linalg.norm(X[:, None] - X[None], axis=2) + np.eye(len(X)) * 1e9
    if dX.min() < DUPLICATE_MM:
        i, j = np.unravel_index(np.argmin(dX), dX.shape)
        return None, None, None, None, None, f"CT fiducials {i} and {j} coincide (duplicate points)"
    dP = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(len(pts)) * 1e9
    if dP.min() < DUPLICATE_PX:
        i, j = np.unravel_index(np.argmin(dP), dP.shape)
        return None, None, None, None, None, f"image points {i} and {j} coincide (duplicate points)"
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    if s[1] < COPLANAR_RATIO * s[0]:
        return None, None, None, None, None, "CT fiducials are collinear: the pose is not determined"
    if s[2] < COPLANAR_RATIO * s[0]:
        return None, None, None, None, None, ("CT fiducials are (nearly) coplanar: matching without pairing "
                                              "is ambiguous for planar layouts; spread them in depth")
    return X, pts, K, dist, prior, ""


def register(fiducials_ct, image_points, K, dist=None, radius_mm=None, method="robust", prior=None,
             options: RobustOptions | None = None, rng_seed: int = 0) -> Registration:
    """Find which image point is which CT fiducial and the pose ``T_cam_ct`` (mm).

    fiducials_ct: (n, 3) fiducial centres, CT mm (LPS). image_points: (m, 2) detected
    centres in px, any order, possibly missing fiducials and holding stray blobs. K: 3x3
    intrinsics; dist: OpenCV distortion coefficients (points are undistorted first).
    radius_mm: sphere radius; when given the exact ellipse-centre model is used in the fit.
    method: "robust" (product), "paper" (the paper's KD-tree + PSO pipeline) or "naive"
    (plain RANSAC over cv2.solveP3P, the benchmark baseline). prior: the previous frame's
    ``T_cam_ct``; tried first (fast path) and abandoned when it no longer explains the image.

    Never raises for bad data or failed matching: returns ``ok=False`` with a ``reason``.
    Raises :class:`InputError` only for an unknown ``method``.
    """
    t0 = time.perf_counter()
    if method not in METHODS:
        raise InputError(f"unknown registration method {method!r}; use one of {', '.join(METHODS)}")
    X, pts, K, dist, prior, why = _check_inputs(fiducials_ct, image_points, K, dist, radius_mm, prior)
    if why:
        return _fail(method, why, t0)
    radius = float(radius_mm) if radius_mm else None
    opts = options or RobustOptions(accept_rms_px=ACCEPT_RMS_PX)
    xn = undistort_to_normalised(pts, K, dist)
    fxy = np.array([K[0, 0], K[1, 1]])
    timing = {"undistort_s": time.perf_counter() - t0}
    stats: dict = {}
    runner = best = None
    used_prior = False
    ref = None
    pairs: tuple = ()
    if prior is not None:
        from .prior import track_with_prior

        t1 = time.perf_counter()
        pairs, ref, why_not = track_with_prior(prior, X, xn, fxy, radius, opts.final_gate_px, ACCEPT_RMS_PX)
        timing["prior_s"] = time.perf_counter() - t1
        used_prior = ref is not None
        if not used_prior:
            stats["prior_rejected"] = why_not
    if ref is None:
        t1 = time.perf_counter()
        if method == "robust":
            best, runner, stats2 = robust_search(X, xn, fxy, radius, opts)
            pairs, ref = (best.pairs, best.refinement) if best else ((), None)
        elif method == "paper":
            from .paper import paper_register

            pairs, ref, stats2, why = paper_register(X, xn, fxy, radius, opts, rng_seed=rng_seed)
            if ref is None:
                stats.update(stats2)
                return _fail(method, why, t0, timing=timing, stats=stats)
        else:
            from .naive import naive_search

            pairs, ref, stats2 = naive_search(X, xn, K, fxy, radius, opts, rng_seed=rng_seed)
        stats.update(stats2)
        timing["search_s"] = time.perf_counter() - t1
    return _finish(method, X, xn, fxy, radius, pairs, ref, best, runner, opts, t0, timing, stats, used_prior,
                   len(pts))


def _finish(method, X, xn, fxy, radius, pairs, ref, best, runner, opts, t0, timing, stats, used_prior,
            m) -> Registration:
    kw = dict(timing=timing, stats=stats)
    if ref is None or len(pairs) < 4:
        timing["total_s"] = time.perf_counter() - t0
        return Registration(ok=False, method=method, reason=(
            f"no pose explains at least 4 image points as fiducials (best: {len(pairs)})"
            if len(pairs) < 4 else "pose refinement failed"), **kw)
    ii = np.array([p[0] for p in pairs])
    mi = np.array([p[1] for p in pairs])
    T = ref.T
    res = ref.residuals
    mags = np.linalg.norm(res, axis=1)
    rms = float(np.sqrt(np.mean(mags**2)))
    sigma = sigma_from_residuals(res)
    reg = Registration(
        ok=True, reason="", method=method, T_cam_ct=T, pairs=[(int(a), int(b)) for a, b in pairs],
        fre_mm=fre_mm(T, X[mi], xn[ii], radius), reprojection_rms_px=rms, residuals_px=mags,
        residual_vectors_px=-res, unmatched_image_indices=sorted(set(range(m)) - set(ii.tolist())),
        unmatched_fiducial_indices=sorted(set(range(len(X))) - set(mi.tolist())),
        sigma_px=sigma, pose_covariance=pose_covariance(ref.JtJ, sigma), used_prior=used_prior,
        sigma_dof=2 * len(res) - 6, **kw)
    Xc = X @ T[:3, :3].T + T[:3, 3]
    reason = ""
    if not np.all(np.isfinite(T)):
        reason = "pose is not finite"
    elif np.any(Xc[mi, 2] <= (radius or 0.0)):
        reason = "pose puts matched fiducials behind the camera"
    elif rms > ACCEPT_RMS_PX or mags.max() > ACCEPT_MAX_PX:
        reason = f"reprojection error too large (RMS {rms:.1f} px, max {mags.max():.1f} px)"
    elif runner is not None and best is not None and is_ambiguous(best, runner, opts):
        reason = (f"ambiguous: two different assignments of {len(pairs)} points explain the image "
                  f"(RMS {rms:.2f} px vs {runner.rms_px:.2f} px)")
        stats["ambiguous_pairs"] = list(runner.pairs)
    if reason:
        # A refused result carries no pose: the rejected fit stays in ``stats`` for diagnosis.
        stats["rejected_T_cam_ct"] = reg.T_cam_ct
        stats["rejected_pairs"] = reg.pairs
        reg.ok = False
        reg.reason = reason
        reg.T_cam_ct = None
        reg.pose_covariance = None
        reg.pairs = []
    timing["total_s"] = time.perf_counter() - t0
    return reg
