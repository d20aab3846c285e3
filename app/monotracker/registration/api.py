"""``register()``: the public entry point (input checks, dispatch, acceptance, report)."""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import numpy as np

from monotracker.errors import InputError

from .pnp import Refinement
from .projection import undistort_to_normalised
from .report import fre_mm, pose_covariance, sigma_from_residuals
from .result import Registration
from .robust import Candidate, RobustOptions, is_ambiguous, robust_search

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
#: Distortion vector lengths OpenCV accepts.
DIST_SIZES = (4, 5, 8, 12, 14)


# --------------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CheckedInputs:
    """The inputs of :func:`register` once they passed every check of :func:`_input_problem`."""

    fiducials_ct: np.ndarray        # (n, 3) float, CT LPS mm, n >= 4, finite, distinct, not planar
    image_points: np.ndarray        # (m, 2) float px, m >= 4, finite, distinct
    K: np.ndarray                   # (3, 3) float, finite, positive focal lengths (px)
    dist: np.ndarray | None         # (4|5|8|12|14,) OpenCV distortion coefficients, or None
    radius_mm: float | None         # sphere radius (mm) > 0, or None
    prior: np.ndarray | None        # (4, 4) finite T_cam_ct prior, or None (a broken prior is dropped)


#: Stands for an argument that could not be read as numbers (``None`` means "not given").
_NOT_NUMERIC = object()


def _floats(value):
    """``value`` as a float array, or ``_NOT_NUMERIC``."""
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return _NOT_NUMERIC


def _float_or_nan(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def _closest_pair(P: np.ndarray) -> tuple[int, int, float]:
    """The two rows of ``P`` (k, d) closest to each other, and their distance."""
    d = np.linalg.norm(P[:, None] - P[None], axis=2) + np.eye(len(P)) * 1e9
    i, j = np.unravel_index(np.argmin(d), d.shape)
    return int(i), int(j), float(d[i, j])


def _principal_spread(X: np.ndarray) -> np.ndarray:
    """Singular values (descending) of the centred point set: its spread along each axis."""
    return np.linalg.svd(X - X.mean(axis=0), compute_uv=False)


@functools.lru_cache(maxsize=8)
def _ct_geometry_of(shape: tuple, data: bytes) -> tuple:
    X = np.frombuffer(data, float).reshape(shape)
    return _closest_pair(X), _principal_spread(X)


def _ct_geometry(X: np.ndarray) -> tuple:
    """(closest pair of CT fiducials (i, j, mm), principal spread) of ``X`` (n, 3) mm, kept for
    the last 8 fiducial sets (keyed by their values): a tracker registers the same set every
    frame (~0.2 ms of the frame's budget each time; issue 29)."""
    X = np.ascontiguousarray(X, float)
    return _ct_geometry_of(X.shape, X.tobytes())


def _input_problem(X, pts, K, dist, radius_mm) -> str:
    """The reason of the first failed check, in checklist order; "" when every check passes.

    Each check may assume the ones above it passed: numbers, then shapes, then values,
    then counts, then geometry.
    """
    if any(a is _NOT_NUMERIC for a in (X, pts, K)):
        return "inputs are not numeric arrays"
    if X.ndim != 2 or X.shape[1] != 3:
        return f"fiducials_ct must be (n, 3) mm, got shape {X.shape}"
    if pts.ndim != 2 or pts.shape[1] != 2:
        return f"image_points must be (m, 2) px, got shape {pts.shape}"
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        return "K must be a finite 3x3 intrinsic matrix with positive focal lengths"
    if dist is _NOT_NUMERIC:
        return "dist is not numeric"
    if dist is not None and (dist.size not in DIST_SIZES or not np.all(np.isfinite(dist))):
        return "dist must hold 4, 5, 8, 12 or 14 finite OpenCV coefficients"
    if radius_mm is not None and not (np.isfinite(radius_mm) and radius_mm > 0):
        return "radius_mm must be a positive number of mm or None"
    if not np.all(np.isfinite(X)):
        return "fiducials_ct contains NaN or infinite values"
    if not np.all(np.isfinite(pts)):
        return "image_points contain NaN or infinite values"
    if len(X) < 4:
        return f"only {len(X)} CT fiducials; need at least 4"
    if len(pts) < 4:
        return f"only {len(pts)} image points; need at least 4 fiducials in view"
    (i, j, d), spread = _ct_geometry(X)
    if d < DUPLICATE_MM:
        return f"CT fiducials {i} and {j} coincide (duplicate points)"
    i, j, d = _closest_pair(pts)
    if d < DUPLICATE_PX:
        return f"image points {i} and {j} coincide (duplicate points)"
    if spread[1] < COPLANAR_RATIO * spread[0]:
        return "CT fiducials are collinear: the pose is not determined"
    if spread[2] < COPLANAR_RATIO * spread[0]:
        return ("CT fiducials are (nearly) coplanar: matching without pairing "
                "is ambiguous for planar layouts; spread them in depth")
    return ""


def _check_inputs(fiducials_ct, image_points, K, dist, radius_mm, prior) -> tuple[CheckedInputs | None, str]:
    """Reads the arguments of :func:`register` as arrays and runs the checklist.

    Returns ``(CheckedInputs, "")``, or ``(None, reason)`` for the first failed check.
    """
    X = _floats(fiducials_ct)
    pts = _floats(image_points)
    if pts is not _NOT_NUMERIC and pts.size == 0:
        pts = pts.reshape(0, 2)
    K = _floats(K)
    if dist is not None:
        dist = _floats(dist)
        dist = dist if dist is _NOT_NUMERIC else dist.ravel()
    if radius_mm is not None:
        radius_mm = _float_or_nan(radius_mm)
    why = _input_problem(X, pts, K, dist, radius_mm)
    if why:
        return None, why
    if prior is not None:
        prior = _floats(prior)
        if prior is _NOT_NUMERIC or prior.shape != (4, 4) or not np.all(np.isfinite(prior)):
            prior = None  # a broken prior is ignored: the full search does not need it
    return CheckedInputs(fiducials_ct=X, image_points=pts, K=K, dist=dist, radius_mm=radius_mm, prior=prior), ""


# --------------------------------------------------------------------------------------------
# One register() call: search, then acceptance
# --------------------------------------------------------------------------------------------

@dataclass
class _Run:
    """What every stage of one :func:`register` call shares."""

    method: str
    inputs: CheckedInputs
    xn: np.ndarray                  # (m, 2) undistorted image points, normalised coordinates
    fxy: np.ndarray                 # (2,) focal lengths px: residuals are in equivalent px
    opts: RobustOptions
    t0: float                       # perf_counter() at the call's start
    timing: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)

    @property
    def radius(self) -> float | None:
        return self.inputs.radius_mm


@dataclass
class _Found:
    """A candidate answer: (image index, fiducial index) pairs and the refined pose."""

    pairs: tuple = ()
    ref: Refinement | None = None
    best: Candidate | None = None       # robust search only: best and runner-up assignments
    runner: Candidate | None = None
    used_prior: bool = False


def _fail(method: str, reason: str, t0: float, timing: dict | None = None, **kw) -> Registration:
    timing = dict(timing or {})
    timing["total_s"] = time.perf_counter() - t0
    return Registration(ok=False, reason=reason, method=method, timing=timing, **kw)


def register(fiducials_ct, image_points, K, dist=None, radius_mm=None, method="robust", prior=None,
             options: RobustOptions | None = None, rng_seed: int = 0) -> Registration:
    """Find which image point is which CT fiducial and the pose ``T_cam_ct`` (mm).

    Args:
        fiducials_ct: (n, 3) float, CT LPS mm: fiducial (sphere) centres, n >= 4, not coplanar.
        image_points: (m, 2) float, px: detected centres in the raw (distorted) image, any
            order; fiducials may be missing and stray blobs present. m >= 4.
        K: (3, 3) camera intrinsics, px (OpenCV convention).
        dist: OpenCV distortion coefficients (4, 5, 8, 12 or 14 values) or None; the points
            are undistorted before matching.
        radius_mm: sphere radius, mm, or None. When given, the fit uses the exact projected
            ellipse centre of a sphere instead of the projected sphere centre.
        method: "robust" (the product's search), "paper" (the paper's KD-tree + PSO pipeline)
            or "naive" (RANSAC over cv2.solveP3P, the benchmark baseline).
        prior: (4, 4) ``T_cam_ct`` of the previous frame (mm) or None. Tried first (fast
            path) and abandoned for the full search when it no longer explains the image; a
            prior that is not a finite 4x4 is ignored.
        options: search tunables (:class:`~.robust.RobustOptions`); defaults when None.
        rng_seed: seed of the random stages ("paper" and "naive"); "robust" is deterministic.

    Returns:
        :class:`~.result.Registration`: with ``ok=True``, ``T_cam_ct`` (4x4, CT mm -> OpenCV
        camera mm), ``pairs`` (image index, fiducial index), residuals, FRE, pose covariance
        and ``timing``; with ``ok=False``, ``T_cam_ct=None`` and a one-line ``reason``.

    Refuses (ok=False, reason):
        non-numeric inputs or wrong shapes; K not finite or focal lengths <= 0; a bad ``dist``
        length; ``radius_mm`` not a positive number; NaN/inf points; fewer than 4 fiducials or
        image points; duplicate fiducials (< ``DUPLICATE_MM``) or image points
        (< ``DUPLICATE_PX``); collinear or (nearly) coplanar fiducials; no pose explaining at
        least 4 points; a pose with fiducials behind the camera; reprojection RMS above
        ``ACCEPT_RMS_PX`` or any residual above ``ACCEPT_MAX_PX``; two different assignments
        that explain the image about equally well (ambiguous).

    Raises:
        InputError: only for an unknown ``method``; bad data never raises.
    """
    t0 = time.perf_counter()
    if method not in METHODS:
        raise InputError(f"unknown registration method {method!r}; use one of {', '.join(METHODS)}")
    inputs, why = _check_inputs(fiducials_ct, image_points, K, dist, radius_mm, prior)
    if why:
        return _fail(method, why, t0)
    K = inputs.K
    run = _Run(method=method, inputs=inputs,
               xn=undistort_to_normalised(inputs.image_points, K, inputs.dist),
               fxy=np.array([K[0, 0], K[1, 1]]),
               opts=options or RobustOptions(accept_rms_px=ACCEPT_RMS_PX), t0=t0)
    run.timing["undistort_s"] = time.perf_counter() - t0
    found = _track_prior(run) if inputs.prior is not None else _Found()
    if found.ref is None:
        found, why = _search(run, rng_seed)
        if why:
            return _fail(method, why, t0, timing=run.timing, stats=run.stats)
    return _finish(run, found)


def _track_prior(run: _Run) -> _Found:
    """The fast path: the previous pose re-fitted to this image (``ref`` None if it does not fit)."""
    from .prior import track_with_prior

    t1 = time.perf_counter()
    pairs, ref, why_not = track_with_prior(run.inputs.prior, run.inputs.fiducials_ct, run.xn, run.fxy,
                                           run.radius, run.opts.final_gate_px, ACCEPT_RMS_PX)
    run.timing["prior_s"] = time.perf_counter() - t1
    if ref is None:
        run.stats["prior_rejected"] = why_not
    return _Found(pairs=pairs, ref=ref, used_prior=ref is not None)


def _search(run: _Run, rng_seed: int) -> tuple[_Found, str]:
    """The full correspondence search of ``run.method``; the str is the paper method's reason
    for giving up ("" otherwise)."""
    X, xn, fxy, radius, opts = run.inputs.fiducials_ct, run.xn, run.fxy, run.radius, run.opts
    t1 = time.perf_counter()
    if run.method == "robust":
        best, runner, stats = robust_search(X, xn, fxy, radius, opts)
        found = _Found(runner=runner)
        if best is not None:
            found = _Found(pairs=best.pairs, ref=best.refinement, best=best, runner=runner)
    elif run.method == "paper":
        from .paper import paper_register

        pairs, ref, stats, why = paper_register(X, xn, fxy, radius, opts, rng_seed=rng_seed)
        if ref is None:
            run.stats.update(stats)
            return _Found(), why
        found = _Found(pairs=pairs, ref=ref)
    else:
        from .naive import naive_search

        pairs, ref, stats = naive_search(X, xn, run.inputs.K, fxy, radius, opts, rng_seed=rng_seed)
        found = _Found(pairs=pairs, ref=ref)
    run.stats.update(stats)
    run.timing["search_s"] = time.perf_counter() - t1
    return found, ""


def _refusal(run: _Run, found: _Found, T: np.ndarray, rms: float, max_px: float) -> str:
    """Acceptance checklist of a fitted pose: the reason of the first failed gate, or ""."""
    X, radius, mi = run.inputs.fiducials_ct, run.radius, [p[1] for p in found.pairs]
    if not np.all(np.isfinite(T)):
        return "pose is not finite"
    Xc = X @ T[:3, :3].T + T[:3, 3]
    if np.any(Xc[mi, 2] <= (radius or 0.0)):
        return "pose puts matched fiducials behind the camera"
    if rms > ACCEPT_RMS_PX or max_px > ACCEPT_MAX_PX:
        return f"reprojection error too large (RMS {rms:.1f} px, max {max_px:.1f} px)"
    if found.runner is not None and found.best is not None and is_ambiguous(found.best, found.runner, run.opts):
        run.stats["ambiguous_pairs"] = list(found.runner.pairs)
        return (f"ambiguous: two different assignments of {len(found.pairs)} points explain the image "
                f"(RMS {rms:.2f} px vs {found.runner.rms_px:.2f} px)")
    return ""


def _finish(run: _Run, found: _Found) -> Registration:
    """The result of ``found``: the report of the fit, refused when an acceptance gate fails."""
    X, xn, pairs, ref = run.inputs.fiducials_ct, run.xn, found.pairs, found.ref
    timing, stats = run.timing, run.stats
    if ref is None or len(pairs) < 4:
        timing["total_s"] = time.perf_counter() - run.t0
        return Registration(ok=False, method=run.method, reason=(
            f"no pose explains at least 4 image points as fiducials (best: {len(pairs)})"
            if len(pairs) < 4 else "pose refinement failed"), timing=timing, stats=stats)
    ii = np.array([p[0] for p in pairs])
    mi = np.array([p[1] for p in pairs])
    T = ref.T
    res = ref.residuals
    mags = np.linalg.norm(res, axis=1)
    rms = float(np.sqrt(np.mean(mags**2)))
    sigma = sigma_from_residuals(res)
    m = len(run.inputs.image_points)
    reg = Registration(
        ok=True, reason="", method=run.method, T_cam_ct=T, pairs=[(int(a), int(b)) for a, b in pairs],
        fre_mm=fre_mm(T, X[mi], xn[ii], run.radius), reprojection_rms_px=rms, residuals_px=mags,
        residual_vectors_px=-res, unmatched_image_indices=sorted(set(range(m)) - set(ii.tolist())),
        unmatched_fiducial_indices=sorted(set(range(len(X))) - set(mi.tolist())),
        sigma_px=sigma, pose_covariance=pose_covariance(ref.JtJ, sigma), used_prior=found.used_prior,
        sigma_dof=2 * len(res) - 6, timing=timing, stats=stats)
    reason = _refusal(run, found, T, rms, float(mags.max()))
    if reason:
        # A refused result carries no pose: the rejected fit stays in ``stats`` for diagnosis.
        stats["rejected_T_cam_ct"] = reg.T_cam_ct
        stats["rejected_pairs"] = reg.pairs
        reg.ok = False
        reg.reason = reason
        reg.T_cam_ct = None
        reg.pose_covariance = None
        reg.pairs = []
    timing["total_s"] = time.perf_counter() - run.t0
    return reg
