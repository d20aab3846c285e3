"""Sub-voxel least-squares fits of a blurred ball (alone, or resting on / sunk into a blurred
scalp plane) to raw CT voxel values at LPS points, mm and HU (:mod:`monotracker.ct.fiducials`)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.special import erfc

import threading

from monotracker.ct import fit_kernels, label_kernels

_SQRT2 = np.sqrt(2.0)
_INV_SQRT_PI = 1.0 / np.sqrt(np.pi)


#: Which solver the fits use: "compiled" (:mod:`.fit_kernels`, numba) or "scipy" (SciPy's
#: ``least_squares``, the reference; ``tests/ct/test_fit_kernels.py`` checks they agree).
SOLVER = "compiled"
_MODELS = {"sphere": fit_kernels.MODEL_SPHERE, "surface": fit_kernels.MODEL_SURFACE}
_LOSSES = {"soft_l1": fit_kernels.LOSS_SOFT_L1, "cauchy": fit_kernels.LOSS_CAUCHY}


#: A compiled fit of at least this many voxels first converges on every :data:`SUBSAMPLE`-th
#: of them (in the order given: the C order of a box, so an even lattice), then is polished on
#: all from there; the result is the minimum of the full cost as before (same tolerances), in
#: fewer voxel evaluations (the polish takes a few steps; on the whole-head phantoms of
#: ``benchmarks/ct_detection.py``: 1.01 -> 0.71 M with dental metal, 0.86 -> 0.42 M without).
SUBSAMPLE_MIN_POINTS = 2400
SUBSAMPLE = 6
#: The compiled fits' extra stopping tests (:func:`.fit_kernels.robust_lm`): the undamped
#: Gauss-Newton step predicts a decrease below this fraction of the cost (SciPy's ``ftol``) with
#: a trusted model (for the polish on all voxels: from the start, a converged subsample fit);
#: or, after a rejected step, would move the centre and radius by at most
#: :data:`STOP_STEP_MM` (a thousandth of the 0.1 mm the detection is held to).
STOP_DECREMENT = 1e-8
STOP_STEP_MM = 1e-4


def _compiled_fit(model: str, pts: np.ndarray, values: np.ndarray, M: np.ndarray | None, x0: np.ndarray, lo: np.ndarray,
                  hi: np.ndarray, f_scale: float, max_nfev: int, loss: str) -> tuple[np.ndarray, float, bool]:
    """:func:`.fit_kernels.robust_lm` with SciPy's default tolerances (1e-8) and the extra
    stopping tests (:data:`STOP_DECREMENT`, :data:`STOP_STEP_MM`); started from a fit on a
    subsample when there are many voxels (:data:`SUBSAMPLE_MIN_POINTS`)."""
    use_M = M is not None
    M = np.zeros((3, 3)) if M is None else np.ascontiguousarray(M, float)
    pts = np.ascontiguousarray(pts, float)
    values = np.ascontiguousarray(values, float)
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    x_start = np.asarray(x0, float)
    polish = False
    if len(pts) >= SUBSAMPLE_MIN_POINTS:
        xs, _, ok_s, _ = fit_kernels.robust_lm(_MODELS[model], x_start, lo, hi, np.ascontiguousarray(pts[::SUBSAMPLE]),
                                               np.ascontiguousarray(values[::SUBSAMPLE]), M, use_M, float(f_scale),
                                               _LOSSES[loss], int(max_nfev), 1e-8, 1e-8, 1e-8, STOP_DECREMENT, False,
                                               STOP_STEP_MM)
        if ok_s and np.all(np.isfinite(xs)):
            x_start, polish = xs, True
    x, rms, ok, _ = fit_kernels.robust_lm(_MODELS[model], x_start, lo, hi, pts, values, M, use_M,
                                          float(f_scale), _LOSSES[loss], int(max_nfev), 1e-8, 1e-8, 1e-8, STOP_DECREMENT,
                                          polish, STOP_STEP_MM)
    return x, float(rms), bool(ok)


def _bounded_robust_fit(resid, jac, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, f_scale: float,
                        max_nfev: int, loss: str = "soft_l1") -> tuple[np.ndarray, float, bool]:
    """Soft-L1 least squares of ``resid`` (HU) within bounds ``lo``..``hi``, started at ``x0``
    (clipped inside), with SciPy (the reference solver). Returns ``(params, rms of the inlier
    residuals (|r| < 3 f_scale), success)``."""
    x0 = np.clip(x0, lo + 1e-6, hi - 1e-6)
    res = least_squares(resid, x0, jac=jac, loss=loss, f_scale=f_scale, bounds=(lo, hi), x_scale="jac",
                        max_nfev=max_nfev)
    r = res.fun
    inl = np.abs(r) < 3.0 * f_scale
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("inf")
    return res.x, rms, bool(res.success)


class _LastCall:
    """``f(p)`` remembered for the last ``p``: least_squares asks for the residuals and then
    the Jacobian at the same parameters, which share the model's terms (computed once)."""

    def __init__(self, f):
        self.f, self.key, self.value = f, None, None

    def __call__(self, p: np.ndarray):
        key = np.asarray(p, float).tobytes()
        if key != self.key:
            self.key, self.value = key, self.f(p)
        return self.value


def _quad(e: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``e_i^T M e_i`` for each row of ``e`` (n, 3) (an einsum "ij,jk,ik->i" is several times
    slower for 3 x 3)."""
    return np.sum((e @ M) * e, axis=1)


def _sphere_model(params: np.ndarray, pts: np.ndarray, M: np.ndarray | None = None):
    c, r, s, H, b = params[:3], params[3], params[4], params[5], params[6]
    rel = pts - c
    dist = np.sqrt(np.sum(rel * rel, axis=1))
    if M is None:
        sF = np.full(len(pts), s)
    else:
        e = rel / np.maximum(dist, 1e-9)[:, None]
        sF = np.sqrt(s * s + _quad(e, M))
    u = (dist - r) / (_SQRT2 * sF)
    fill = 0.5 * erfc(u)
    return b + (H - b) * fill, fill, (dist, rel, u, sF)


def fit_blurred_sphere(pts: np.ndarray, values: np.ndarray, x0: np.ndarray, f_scale: float,
                       box_cov: np.ndarray | None = None, r_bounds: tuple[float, float] = (0.3, 30.0), loss: str = "soft_l1",
                       solver: str | None = None):
    """Least-squares fit of a blurred ball to voxel values at LPS points ``pts`` (n, 3).

    Parameters ``[cx, cy, cz, r, s, H, b]``: centre and radius (mm), edge sigma (mm), inside
    and background levels (HU). ``box_cov`` (3x3 mm^2, the voxel box's covariance in LPS):
    an edge with normal ``e`` is then blurred by ``sqrt(s**2 + e^T box_cov e)`` (the slice
    profile: thick slices blur along z more than in-plane) and ``s`` is the scanner's PSF.
    ``solver``: "compiled" or "scipy" (the reference); None: :data:`SOLVER`.
    Returns (params, inlier RMS residual HU, success).
    """
    M = None if box_cov is None else np.asarray(box_cov, float)
    lo = np.r_[x0[:3] - 3.0, r_bounds[0], 0.05, -np.inf, -np.inf]
    hi = np.r_[x0[:3] + 3.0, r_bounds[1], 5.0 if M is None else 1.5, np.inf, np.inf]
    if (solver or SOLVER) == "compiled":
        return _compiled_fit("sphere", pts, values, M, x0, lo, hi, f_scale, 60, loss)
    parts = _LastCall(lambda p: _sphere_model(p, pts, M))

    def resid(p):
        m, _, _ = parts(p)
        return m - values

    def jac(p):
        s, H, b = p[4], p[5], p[6]
        _, fill, (dist, rel, u, sF) = parts(p)
        g = -_INV_SQRT_PI * np.exp(-u * u)  # d fill / d u
        du_ddist = 1.0 / (_SQRT2 * sF)
        k = (H - b) * g
        J = np.empty((len(pts), 7))
        unit = rel / np.maximum(dist, 1e-9)[:, None]
        J[:, :3] = -(k * du_ddist)[:, None] * unit
        J[:, 3] = -k * du_ddist
        J[:, 4] = -k * u * s / (sF * sF)
        J[:, 5] = fill
        J[:, 6] = 1.0 - fill
        return J

    return _bounded_robust_fit(resid, jac, x0, lo, hi, f_scale, max_nfev=60, loss=loss)


def _unit_from_angles(theta: float, phi: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    st, ct, sp, cp = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
    n = np.array([st * cp, st * sp, ct])
    return n, np.array([ct * cp, ct * sp, -st]), np.array([-st * sp, st * cp, 0.0])


def fit_ball_on_surface(pts: np.ndarray, values: np.ndarray, x0: np.ndarray, f_scale: float, box_cov: np.ndarray | None = None,
                        r_bounds: tuple[float, float] = (0.3, 30.0), max_tissue_hu: float = np.inf, loss: str = "soft_l1",
                        solver: str | None = None):
    """Least-squares fit of a blurred ball resting on a blurred plane surface (the scalp).

    The background is ``b_out`` on one side of the plane ``n . (x - c) = h`` and ``b_in`` on
    the other (``n`` from the ball towards the tissue, angles ``theta, phi``), blurred with the
    same edge sigma ``s`` as the ball; the ball occludes it:
    ``v = bg (1 - fill) + H fill``. Without this the scalp under a ball pulls a plain sphere
    fit towards the skin by ~0.015 mm at 0.45 mm PSF and ~0.05 mm at 0.8 mm.
    ``box_cov`` (3x3, mm^2): the voxel box's covariance in LPS, ``D diag(w**2 / 12) D^T``;
    with it an edge with normal ``e`` is blurred by ``sqrt(s**2 + e^T box_cov e)``, so thick
    slices blur along z more than in-plane, as in the scanner; ``s`` is then the PSF sigma.
    Parameters ``[cx, cy, cz, r, s, H, b_out, b_in, theta, phi, h]``. ``solver``: "compiled"
    or "scipy" (the reference); None: :data:`SOLVER`. Returns (params, inlier RMS residual HU,
    success).
    """
    M = np.zeros((3, 3)) if box_cov is None else np.asarray(box_cov, float)
    # the tissue must stay fainter than the ball (``max_tissue_hu``), or a half space of "tissue"
    # as dense as the ball can stand in for part of it
    lo = np.r_[x0[:3] - 3.0, r_bounds[0], 0.05, -np.inf, -np.inf, -np.inf, -np.inf, -np.inf, -np.inf]
    hi = np.r_[x0[:3] + 3.0, r_bounds[1], 5.0, np.inf, max_tissue_hu, max_tissue_hu, np.inf, np.inf, np.inf]
    if (solver or SOLVER) == "compiled":
        return _compiled_fit("surface", pts, values, M, x0, lo, hi, f_scale, 80, loss)

    def parts(p):
        c, r, s0, H, bo, bi, th, ph, h = p[:3], p[3], p[4], p[5], p[6], p[7], p[8], p[9], p[10]
        rel = pts - c
        dist = np.sqrt(np.sum(rel * rel, axis=1))
        e = rel / np.maximum(dist, 1e-9)[:, None]
        sF = np.sqrt(s0 * s0 + _quad(e, M))
        u = (dist - r) / (_SQRT2 * sF)
        fill = 0.5 * erfc(u)
        n, dn_dth, dn_dph = _unit_from_angles(th, ph)
        sP = np.sqrt(s0 * s0 + n @ M @ n)
        z = (h - rel @ n) / (_SQRT2 * sP)
        s = (sF, sP, s0)
        pf = 0.5 * erfc(z)
        bg = bo + (bi - bo) * pf
        return c, r, s, H, bo, bi, rel, dist, u, fill, n, dn_dth, dn_dph, z, pf, bg

    parts = _LastCall(parts)

    def resid(p):
        *_, fill, _n, _a, _b, _z, _pf, bg = parts(p)
        return bg * (1.0 - fill) + p[5] * fill - values

    def jac(p):
        # the blur's dependence on the normal direction is left out of the Jacobian (tiny)
        c, r, (sF, sP, s0), H, bo, bi, rel, dist, u, fill, n, dn_dth, dn_dph, z, pf, bg = parts(p)
        kF = 1.0 / (_SQRT2 * sF)
        k2 = 1.0 / (_SQRT2 * sP)
        gF = -_INV_SQRT_PI * np.exp(-u * u) * (H - bg)
        gP = -_INV_SQRT_PI * np.exp(-z * z) * (1.0 - fill) * (bi - bo)
        unit = rel / np.maximum(dist, 1e-9)[:, None]
        J = np.empty((len(pts), 11))
        J[:, :3] = -(gF * kF)[:, None] * unit + (gP * k2)[:, None] * n[None, :]
        J[:, 3] = -gF * kF
        J[:, 4] = -gF * u * s0 / (sF * sF) - gP * z * s0 / (sP * sP)
        J[:, 5] = fill
        J[:, 6] = (1.0 - fill) * (1.0 - pf)
        J[:, 7] = (1.0 - fill) * pf
        J[:, 8] = -gP * k2 * (rel @ dn_dth)
        J[:, 9] = -gP * k2 * (rel @ dn_dph)
        J[:, 10] = gP * k2
        return J

    return _bounded_robust_fit(resid, jac, x0, lo, hi, f_scale, max_nfev=80, loss=loss)


def refine_on_surface(pts: np.ndarray, values: np.ndarray, ball: np.ndarray, f_scale: float, box_cov: np.ndarray | None = None,
                      psf_given: bool = False, ball_hu: float | None = None):
    """Second stage after :func:`fit_blurred_sphere`: when the voxels outside the ball hold two
    clearly different levels (air and the scalp the ball rests on or is sunk into), refit with
    :func:`fit_ball_on_surface`, started with the plane tangent under the ball and through its
    centre (a half-embedded ball); the better fit wins. ``ball`` is the plain fit's (or the
    blob's) ``[c, r, s, H, b]``; ``ball_hu`` the ball level to compare the tissue with.
    Returns (params, rms) or None."""
    c, r, s, H, b = ball[:3], ball[3], ball[4], ball[5], ball[6]
    H = H if ball_hu is None else ball_hu
    rel = pts - c
    dist = np.linalg.norm(rel, axis=1)
    outside = (dist > r + 2.0 * min(s, 0.75)) & (values < b + 0.5 * (H - b))
    if outside.sum() < 20:
        return None
    ov = values[outside]
    split = 0.5 * (np.percentile(ov, 10) + np.percentile(ov, 90))
    bright = outside & (values > split)
    dark = outside & ~bright
    if bright.sum() < 10 or dark.sum() < 10:
        return None
    b_in, b_out = float(np.median(values[bright])), float(np.median(values[dark]))
    if b_in - b_out < max(2.0 * f_scale, 150.0):
        return None
    d = rel[bright].mean(axis=0) - rel[dark].mean(axis=0)
    if np.linalg.norm(d) < 1e-6:
        return None
    n = d / np.linalg.norm(d)
    th, ph = np.arccos(np.clip(n[2], -1, 1)), np.arctan2(n[1], n[0])
    s0 = s if (box_cov is None or psf_given) else float(np.sqrt(max(s * s - np.trace(box_cov) / 3.0, 0.01)))
    best = None
    for h0 in (r, 0.0):
        x0 = np.r_[c, r, s0, H, b_out, min(b_in, b_out + 0.5 * (H - b_out)), th, ph, h0]
        params, rms, ok = fit_ball_on_surface(pts, values, x0, f_scale, box_cov, r_bounds=(0.8 * r, 1.25 * r + 0.2),
                                              max_tissue_hu=b_out + 0.6 * (H - b_out))
        if ok and np.linalg.norm(params[:3] - c) <= 1.5 and (best is None or rms < best[1]):
            best = (params, rms)
        if best is not None and best[1] < 0.5 * f_scale:  # residuals at the noise level: no need for the other start
            break
    return best


_warm_lock = threading.Lock()
_warm_thread: threading.Thread | None = None


def warm_up() -> None:
    """Compile (or load from numba's disk cache) the compiled fits for the argument types that
    :func:`fit_blurred_sphere` and :func:`fit_ball_on_surface` pass during a detection (and
    :func:`.label_kernels.label_stats` of the blob search), on a
    small synthetic ball (~1 000 voxels, milliseconds once compiled). The first detection after
    an install otherwise pays the compilation (a few seconds)."""
    ax = np.arange(-4.0, 4.01, 0.8)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    M = np.diag([0.8**2 / 12.0] * 3)
    truth = np.r_[0.1, -0.1, 0.05, 2.0, 0.4, 2000.0, 0.0]
    vals = _sphere_model(truth, pts, M)[0]
    x0 = np.r_[0.0, 0.0, 0.0, 2.2, 0.4, 1800.0, 50.0]
    fit_blurred_sphere(pts, vals, x0, 60.0, M, solver="compiled")
    fit_blurred_sphere(pts, vals, x0, 60.0, None, solver="compiled")
    xs = np.r_[x0[:6], 0.0, 40.0, 3.0, 0.0, 2.0]
    for loss in ("soft_l1", "cauchy"):
        fit_ball_on_surface(pts, vals, xs, 60.0, M, max_tissue_hu=1000.0, loss=loss, solver="compiled")
    for dt in (np.int16, np.float32, np.float64):  # the fit windows of int16 and float scans (views)
        box = np.zeros((4, 4, 4), dt)[1:, 1:, 1:]
        for sib in (np.zeros((0, 3)), np.ones((1, 3))):
            fit_kernels.fit_window(box, np.zeros(3, np.int64), np.eye(3), np.zeros(3), np.zeros(3), 1.0, M, sib,
                                   np.ones(len(sib)), -1024.0, True)
    label_kernels.warm_up()  # the blob search's per-component statistics


def warm_up_in_background() -> threading.Thread:
    """:func:`warm_up` on a daemon thread, once per process (later calls return the same
    thread): started when a CT is loaded, so the compilation overlaps the reading of the
    series instead of delaying the detection that follows. Errors are left to the detection
    (which compiles the same code and reports them there)."""
    global _warm_thread
    with _warm_lock:
        if _warm_thread is None:
            def run():
                try:
                    warm_up()
                except Exception:  # noqa: BLE001 - the detection compiles again and reports
                    pass
            _warm_thread = threading.Thread(target=run, name="ct-fit-warm-up", daemon=True)
            _warm_thread.start()
        return _warm_thread
