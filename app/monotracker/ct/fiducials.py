"""Automatic detection of the sphere fiducials in a CT, in physical LPS millimetres.

Two methods, measured side by side by ``benchmarks/ct_detection.py``:

* :func:`detect_fiducials_paper` - the paper's recipe as a baseline: a fixed grey-value
  threshold, statistical outlier removal, DBSCAN, and the plain centroid of each cluster's
  voxels (Chen et al. 2025 give no numbers for threshold or DBSCAN settings; the ones here are
  what a careful reader would pick, written in the function's docstring).
* :func:`detect_fiducials` - the product method:

  1. **Adaptive threshold** from the volume's own levels (:func:`estimate_levels`): the
     soft-tissue peak and its noise from the histogram, the bone level (98th percentile of the
     voxels denser than tissue), the metal level (the plateau of the voxels clearly denser than
     bone). The threshold is half way between bone and metal, so it follows scanners that
     saturate at 3071 HU, ceramic or titanium balls and noisy low-dose scans alike.
  2. **Clusters in physical mm**: DBSCAN (scikit-learn, ``min_samples=1``: connected
     components with an ``eps`` just above the largest voxel spacing) on the LPS positions of
     the voxels above the threshold.
  3. **Shape and size gate** per cluster: too few voxels (noise, streak specks), elongated
     (clips, wires, streaks, dense bony ridges: ratio of the principal axes of the voxel
     boxes, > 1.35), then a sub-voxel
     least-squares fit of a blurred sphere ``b + (H - b) * erfc((|x - c| - r) / (sqrt(2) s)) / 2``
     to the raw voxel values in LPS mm (robust ``soft_l1`` loss, so the scalp the ball rests on
     does not pull it), then, where the ball rests on tissue, a refit that models the scalp
     under it as a blurred plane (:func:`fit_ball_on_surface`; removes a ~0.015-0.05 mm pull
     towards the skin; the edge blur follows the voxel box, so thick slices blur along z
     more than in-plane). The fit gives the centre, the radius and the residual; balls whose
     radius disagrees with ``radius_mm`` (or, when not given, with the other balls' median) or
     whose residual says "not a sphere" are rejected, with the reason kept.
  4. **Score** in [0, 1] per fiducial: ``exp(-residual / 0.04)`` (residual = inlier RMS /
     contrast) x ``exp(-(radius deviation / 10 %)^2)`` x ``1 / elongation^2``; a clean ball
     in 18 HU noise scores ~0.75-0.8, anything below ~0.3 deserves a look.

Detection never raises for an empty result: ``ok=False`` with a ``reason``.
Fiducials are returned sorted from superior to inferior (descending S), for a stable order.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.special import erfc
from sklearn.cluster import DBSCAN
from threadpoolctl import threadpool_limits

from monotracker.ct.blob_search import search_blobs, threshold_ladder
from monotracker.ct.kit import FiducialKit
from monotracker.ct.volume import Volume

#: Bounds of a plausible fiducial radius when none is given, mm.
RADIUS_RANGE_MM = (1.0, 12.0)
#: Largest ratio of the principal axes of a thresholded blob still accepted as a ball.
MAX_ELONGATION = 1.35
#: Largest relative disagreement between a blob's fitted radius and the expected radius.
RADIUS_TOLERANCE = 0.2
#: Largest fit residual (RMS of inliers / contrast) for a sphere.
MAX_REL_RESIDUAL = 0.08
#: Refuse to cluster more candidate voxels than this (threshold must be wrong).
MAX_CANDIDATES = 2_000_000


@dataclass
class Fiducial:
    """One detected ball: centre (LPS mm), fitted radius (mm), score in [0, 1]."""

    centre_lps: np.ndarray
    radius_mm: float
    score: float
    peak_hu: float = float("nan")
    n_voxels: int = 0
    elongation: float = 1.0
    fit_residual: float = 0.0

    def to_dict(self) -> dict:
        return {
            "centre_lps_mm": [round(float(x), 4) for x in self.centre_lps],
            "radius_mm": round(float(self.radius_mm), 3),
            "score": round(float(self.score), 3),
            "peak_hu": round(float(self.peak_hu), 1),
            "n_voxels": int(self.n_voxels),
        }


@dataclass
class RejectedBlob:
    """A dense blob that is not taken as a fiducial, and why."""

    centre_lps: np.ndarray
    reason: str
    n_voxels: int = 0
    radius_mm: float = float("nan")

    def to_dict(self) -> dict:
        return {
            "centre_lps_mm": [round(float(x), 3) for x in self.centre_lps],
            "reason": self.reason,
            "n_voxels": int(self.n_voxels),
            "radius_mm": None if not np.isfinite(self.radius_mm) else round(float(self.radius_mm), 3),
        }


@dataclass
class FiducialDetection:
    """Result of a detection. ``centres`` is (n, 3) LPS mm in the order of ``fiducials``."""

    ok: bool
    reason: str
    fiducials: list[Fiducial] = field(default_factory=list)
    rejected: list[RejectedBlob] = field(default_factory=list)
    threshold_hu: float = float("nan")
    levels: dict = field(default_factory=dict)
    method: str = "robust"
    elapsed_s: float = 0.0
    notes: list[str] = field(default_factory=list)
    #: The threshold ladder searched, HU (ascending); ``threshold_hu`` is its lowest level.
    thresholds_hu: list[float] = field(default_factory=list)

    @property
    def centres(self) -> np.ndarray:
        if not self.fiducials:
            return np.zeros((0, 3))
        return np.array([f.centre_lps for f in self.fiducials], float)

    @property
    def radii_mm(self) -> np.ndarray:
        return np.array([f.radius_mm for f in self.fiducials], float)

    def to_dict(self) -> dict:
        return {
            "ok": self.ok,
            "reason": self.reason,
            "method": self.method,
            "frame": "LPS",
            "units": "mm",
            "threshold_hu": None if not np.isfinite(self.threshold_hu) else round(float(self.threshold_hu), 1),
            "thresholds_hu": [round(float(t), 1) for t in self.thresholds_hu],
            "levels_hu": {k: round(float(v), 1) for k, v in self.levels.items()},
            "fiducials": [f.to_dict() for f in self.fiducials],
            "rejected": [r.to_dict() for r in self.rejected],
            "elapsed_s": round(self.elapsed_s, 4),
            "notes": list(self.notes),
        }


# ---------------------------------------------------------------------------- levels
def _strided_sample(arr: np.ndarray, target: int = 1_500_000) -> np.ndarray:
    step = max(1, int(round((arr.size / target) ** (1.0 / 3.0))))
    return arr[::step, ::step, ::step]


def _otsu(hist: np.ndarray) -> int:
    """Bin index that best splits a histogram into two classes (Otsu 1979)."""
    w = np.cumsum(hist)
    m = np.cumsum(hist * np.arange(len(hist)))
    total_w, total_m = w[-1], m[-1]
    w1 = total_w - w
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (m / w - (total_m - m) / w1) ** 2 * w * w1
    between[~np.isfinite(between)] = -1.0
    return int(np.argmax(between)) + 1


def estimate_levels(volume: Volume) -> dict:
    """Grey levels of the scan, HU: ``air``, ``tissue`` (soft-tissue peak), ``noise`` (its
    standard deviation); ``bone`` (upper bone level) and ``metal`` (typical value of the
    voxels clearly denser than bone; NaN when there are none), see the comments inside."""
    arr = volume.array
    s = _strided_sample(arr)
    v = np.clip(s.astype(np.int32, copy=False), -1024, 4095).ravel() + 1024
    hist = np.bincount(v, minlength=5120).astype(float)
    hu = np.arange(5120) - 1024
    smooth = np.convolve(hist, np.ones(9) / 9.0, mode="same")
    air_band = (hu >= -1024) & (hu < -500)
    air = float(hu[air_band][np.argmax(smooth[air_band])]) if hist[air_band].sum() else -1000.0
    t_band = (hu >= -250) & (hu <= 250)
    tissue = int(hu[t_band][np.argmax(smooth[t_band])])
    # noise: half width at half maximum of the tissue peak
    peak = smooth[hu == tissue][0]
    lo = tissue
    while lo > -400 and smooth[lo + 1024] > peak / 2:
        lo -= 1
    hi = tissue
    while hi < 400 and smooth[hi + 1024] > peak / 2:
        hi += 1
    noise = max(1.0, (hi - lo) / 2.355)
    # bone vs metal, two ways, the first that separates them clearly wins:
    # (a) bone = 98th percentile of everything denser than soft tissue, metal = typical value of
    #     what is clearly denser than that (right when fiducials are a small share: a head);
    # (b) Otsu's split of that histogram (right when they are a large share: a small field of
    #     view around the balls, large balls).
    flat = arr.reshape(-1)
    dense = flat[np.flatnonzero(flat > tissue + 250)]
    gap = max(400.0, 10.0 * noise)
    bone, metal = tissue + 250.0, float("nan")
    if dense.size > 50:
        bone = float(np.percentile(dense, 98))
        high = dense[dense > bone + max(300.0, 8.0 * noise)]
        if high.size >= 8 and np.percentile(high, 90) - bone >= gap:
            metal = float(np.percentile(high, 90))
        else:
            dh = np.bincount(np.clip(dense.astype(np.int64) + 1024, 0, 5119), minlength=5120).astype(float)
            split = _otsu(dh) - 1024
            low, high = dense[dense < split], dense[dense >= split]
            if low.size > 50 and high.size >= 8:
                b2, m2 = float(np.percentile(low, 98)), float(np.median(high))
                if m2 - b2 >= gap:
                    bone, metal = b2, m2
    return {"air": air, "tissue": float(tissue), "noise": noise, "bone": bone, "metal": metal}


# ---------------------------------------------------------------------------- sphere fit
_SQRT2 = np.sqrt(2.0)
_INV_SQRT_PI = 1.0 / np.sqrt(np.pi)


def _bounded_robust_fit(resid, jac, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, f_scale: float,
                        max_nfev: int, loss: str = "soft_l1") -> tuple[np.ndarray, float, bool]:
    """Soft-L1 least squares of ``resid`` (HU) within bounds ``lo``..``hi``, started at ``x0``
    (clipped inside). Returns ``(params, rms of the inlier residuals (|r| < 3 f_scale), success)``."""
    x0 = np.clip(x0, lo + 1e-6, hi - 1e-6)
    res = least_squares(resid, x0, jac=jac, loss=loss, f_scale=f_scale, bounds=(lo, hi), x_scale="jac",
                        max_nfev=max_nfev)
    r = res.fun
    inl = np.abs(r) < 3.0 * f_scale
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("inf")
    return res.x, rms, bool(res.success)


def _sphere_model(params: np.ndarray, pts: np.ndarray, M: np.ndarray | None = None):
    c, r, s, H, b = params[:3], params[3], params[4], params[5], params[6]
    rel = pts - c
    dist = np.sqrt(np.sum(rel * rel, axis=1))
    if M is None:
        sF = np.full(len(pts), s)
    else:
        e = rel / np.maximum(dist, 1e-9)[:, None]
        sF = np.sqrt(s * s + np.einsum("ij,jk,ik->i", e, M, e))
    u = (dist - r) / (_SQRT2 * sF)
    fill = 0.5 * erfc(u)
    return b + (H - b) * fill, fill, (dist, rel, u, sF)


def fit_blurred_sphere(pts: np.ndarray, values: np.ndarray, x0: np.ndarray, f_scale: float,
                       box_cov: np.ndarray | None = None, r_bounds: tuple[float, float] = (0.3, 30.0), loss: str = "soft_l1"):
    """Least-squares fit of a blurred ball to voxel values at LPS points ``pts`` (n, 3).

    Parameters ``[cx, cy, cz, r, s, H, b]``: centre and radius (mm), edge sigma (mm), inside
    and background levels (HU). ``box_cov`` (3x3 mm^2, the voxel box's covariance in LPS):
    an edge with normal ``e`` is then blurred by ``sqrt(s**2 + e^T box_cov e)`` (the slice
    profile: thick slices blur along z more than in-plane) and ``s`` is the scanner's PSF.
    Returns (params, inlier RMS residual HU, success).
    """
    M = None if box_cov is None else np.asarray(box_cov, float)

    def resid(p):
        m, _, _ = _sphere_model(p, pts, M)
        return m - values

    def jac(p):
        c, r, s, H, b = p[:3], p[3], p[4], p[5], p[6]
        _, fill, (dist, rel, u, sF) = _sphere_model(p, pts, M)
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

    lo = np.r_[x0[:3] - 3.0, r_bounds[0], 0.05, -np.inf, -np.inf]
    hi = np.r_[x0[:3] + 3.0, r_bounds[1], 5.0 if M is None else 1.5, np.inf, np.inf]
    return _bounded_robust_fit(resid, jac, x0, lo, hi, f_scale, max_nfev=60, loss=loss)


def _unit_from_angles(theta: float, phi: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    st, ct, sp, cp = np.sin(theta), np.cos(theta), np.sin(phi), np.cos(phi)
    n = np.array([st * cp, st * sp, ct])
    return n, np.array([ct * cp, ct * sp, -st]), np.array([-st * sp, st * cp, 0.0])


def fit_ball_on_surface(pts: np.ndarray, values: np.ndarray, x0: np.ndarray, f_scale: float, box_cov: np.ndarray | None = None,
                        r_bounds: tuple[float, float] = (0.3, 30.0), max_tissue_hu: float = np.inf, loss: str = "soft_l1"):
    """Least-squares fit of a blurred ball resting on a blurred plane surface (the scalp).

    The background is ``b_out`` on one side of the plane ``n . (x - c) = h`` and ``b_in`` on
    the other (``n`` from the ball towards the tissue, angles ``theta, phi``), blurred with the
    same edge sigma ``s`` as the ball; the ball occludes it:
    ``v = bg (1 - fill) + H fill``. Without this the scalp under a ball pulls a plain sphere
    fit towards the skin by ~0.015 mm at 0.45 mm PSF and ~0.05 mm at 0.8 mm.
    ``box_cov`` (3x3, mm^2): the voxel box's covariance in LPS, ``D diag(w**2 / 12) D^T``;
    with it an edge with normal ``e`` is blurred by ``sqrt(s**2 + e^T box_cov e)``, so thick
    slices blur along z more than in-plane, as in the scanner; ``s`` is then the PSF sigma.
    Parameters ``[cx, cy, cz, r, s, H, b_out, b_in, theta, phi, h]``. Returns
    (params, inlier RMS residual HU, success).
    """
    M = np.zeros((3, 3)) if box_cov is None else np.asarray(box_cov, float)

    def parts(p):
        c, r, s0, H, bo, bi, th, ph, h = p[:3], p[3], p[4], p[5], p[6], p[7], p[8], p[9], p[10]
        rel = pts - c
        dist = np.sqrt(np.sum(rel * rel, axis=1))
        e = rel / np.maximum(dist, 1e-9)[:, None]
        sF = np.sqrt(s0 * s0 + np.einsum("ij,jk,ik->i", e, M, e))
        u = (dist - r) / (_SQRT2 * sF)
        fill = 0.5 * erfc(u)
        n, dn_dth, dn_dph = _unit_from_angles(th, ph)
        sP = np.sqrt(s0 * s0 + n @ M @ n)
        z = (h - rel @ n) / (_SQRT2 * sP)
        s = (sF, sP, s0)
        pf = 0.5 * erfc(z)
        bg = bo + (bi - bo) * pf
        return c, r, s, H, bo, bi, rel, dist, u, fill, n, dn_dth, dn_dph, z, pf, bg

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

    # the tissue must stay fainter than the ball (``max_tissue_hu``), or a half space of "tissue"
    # as dense as the ball can stand in for part of it
    lo = np.r_[x0[:3] - 3.0, r_bounds[0], 0.05, -np.inf, -np.inf, -np.inf, -np.inf, -np.inf, -np.inf]
    hi = np.r_[x0[:3] + 3.0, r_bounds[1], 5.0, np.inf, max_tissue_hu, max_tissue_hu, np.inf, np.inf, np.inf]
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


# ---------------------------------------------------------------------------- helpers
def _candidate_points(volume: Volume, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxels above ``threshold``: their (k, j, i) indices and LPS positions."""
    flat = volume.array.reshape(-1)
    idx = np.flatnonzero(flat > threshold)  # far faster than argwhere on a 3D array
    kji = np.column_stack(np.unravel_index(idx, volume.array.shape))
    return kji, volume.zyx_to_lps(kji)


def _principal_axes(pts: np.ndarray, volume: Volume) -> np.ndarray:
    """Semi-axis lengths (mm, descending) of the solid ellipsoid with the covariance of the
    voxels at ``pts`` (LPS mm). Each voxel counts as its box, not its centre (adds
    ``w**2 / 12`` along each grid axis), so thick slices do not make a ball look flat."""
    if len(pts) < 4:
        return np.zeros(3)
    D, w = volume.direction, volume.spacing_mm
    cov = np.cov(pts.T) + (D * (w**2 / 12.0)) @ D.T
    ev = np.linalg.eigvalsh(cov)[::-1]
    return np.sqrt(np.maximum(5.0 * ev, 0.0))


def _window(volume: Volume, kji: np.ndarray, pad_mm: float):
    """Index box around cluster voxels ``kji`` padded by ``pad_mm`` in every direction."""
    pad = np.ceil(pad_mm / volume.spacing_mm[::-1]).astype(int)
    lo = np.maximum(kji.min(axis=0) - pad, 0)
    hi = np.minimum(kji.max(axis=0) + pad + 1, volume.array.shape)
    return lo, hi


# ---------------------------------------------------------------------------- product method
def detect_fiducials(volume: Volume, radius_mm: float | None = None, kit: FiducialKit | None = None,
                     time_budget_s: float = 60.0, cancel=None) -> FiducialDetection:
    """Find the sphere fiducials in ``volume`` (see the module docstring).

    Args:
        volume: the CT (:class:`~monotracker.ct.volume.Volume`, HU, LPS geometry), e.g. from
            :func:`~monotracker.ct.volume.load_volume`.
        radius_mm: nominal ball radius, mm; overrides ``kit.radius_mm``. Without a radius it is
            estimated (each ball's fitted radius, checked against the median of all balls).
        kit: what the balls are (nominal radius mm, density HU; either may be None); None is
            ``FiducialKit()`` (both unknown).
        time_budget_s: wall-clock bound of the search, s, for pathological scans (a note says
            when it stopped and ``reason`` ends with "(search stopped early)").
        cancel: optional callable; once it returns True the search stops the same way (the
            CT job's cancel button and overall timeout).

    Returns:
        :class:`FiducialDetection`: ``fiducials`` (centre LPS mm, sub-voxel; fitted radius mm;
        score in [0, 1]) sorted superior to inferior, ``centres`` as (n, 3) float64 LPS mm,
        ``rejected`` dense blobs with the reason each was not taken, ``notes``, ``levels`` and
        the thresholds searched (HU).

    Refuses (ok=False, reason): nothing denser than the threshold; dense blobs but none a
    sphere of the expected size; no sphere-shaped blob. Never raises for an empty result.
    """
    t0 = time.perf_counter()
    kit = kit or FiducialKit()
    if radius_mm is None:
        radius_mm = kit.radius_mm
    levels = estimate_levels(volume)
    out = FiducialDetection(ok=False, reason="", levels=levels, method="robust")
    vmax = float(np.max(volume.array))
    ladder = threshold_ladder(levels, min(vmax, 3071.0) if kit.density_hu is None else vmax, kit.density_hu)
    out.threshold_hu = float(ladder[0])
    out.thresholds_hu = [float(t) for t in ladder]
    sp = volume.spacing_mm
    voxel_mm3 = float(np.prod(sp))
    min_vox = max(4, int(np.ceil((4.0 / 3.0) * np.pi * 0.8**3 / voxel_mm3)))
    r_max = RADIUS_RANGE_MM[1] if radius_mm is None else (1.0 + RADIUS_TOLERANCE) * float(radius_mm)
    max_vox = int(np.ceil((4.0 / 3.0) * np.pi * (r_max + float(sp.max())) ** 3 / voxel_mm3))
    if vmax <= ladder[0]:
        out.reason = f"nothing denser than {ladder[0]:.0f} HU in this scan: no fiducials"
        out.elapsed_s = time.perf_counter() - t0
        return out

    def fit(kji, T, sibs):
        return _fit_blob(volume, kji, T, sibs, levels, kit)

    # The fits solve tiny (n x 11) problems: BLAS threads only add contention (seen: 0.06 s ->
    # 4.5 s of SVD on a loaded 2-core machine), so run them single-threaded.
    with threadpool_limits(limits=1, user_api="blas"):
        candidates, rejected, stats = search_blobs(volume, ladder, min_vox, max_vox, fit, time_budget_s=time_budget_s,
                                                    tissue_hu=levels["tissue"], noise_hu=levels["noise"], cancel=cancel)
    out.rejected.extend(rejected)
    _size_gate(out, candidates, radius_mm)
    out.fiducials.sort(key=lambda f: -f.centre_lps[2])
    if stats.specks:
        out.notes.append(f"{stats.specks} small or faint fragments ignored (noise, streaks, bone edges)")
    if stats.stopped:
        out.notes.append(stats.stopped)
    out.ok = bool(out.fiducials)
    out.reason = (
        f"{len(out.fiducials)} fiducials found" + (f", {len(out.rejected)} dense blobs rejected" if out.rejected else "")
        if out.ok
        else ("dense blobs found but none is a sphere of the expected size" if out.rejected
              else f"no sphere-shaped blob above {ladder[0]:.0f} HU: no fiducials in this scan")
    )
    if stats.stopped:
        out.reason += " (search stopped early)"
    out.elapsed_s = time.perf_counter() - t0
    return out


def _touching_hint(n: int, voxel_mm3: float, radius_mm: float | None, elong: float) -> str:
    if radius_mm is None or elong < 1.5:
        return ""
    k = n * voxel_mm3 / ((4.0 / 3.0) * np.pi * radius_mm**3)
    return f"; as large as {k:.1f} balls: touching balls that could not be separated?" if 1.6 <= k <= 4.5 else ""


def _fit_blob(volume: Volume, ckji: np.ndarray, T: float, sibs, levels: dict, kit: FiducialKit):
    """Shape gate and sphere fit of one blob (voxel indices ``ckji`` (n, 3) k, j, i).
    Returns ``(candidate dict, None)`` or ``(None, RejectedBlob)``. ``sibs``: neighbouring
    blobs whose voxels are kept out of the fit window."""
    sp = volume.spacing_mm
    voxel_mm3 = float(np.prod(sp))
    arr = volume.array
    noise = levels["noise"]
    n = len(ckji)
    cpts = volume.zyx_to_lps(ckji)
    centroid = cpts.mean(axis=0)
    axes = _principal_axes(cpts, volume)
    elong = float(axes[0] / max(axes[2], 1e-6))
    if elong > MAX_ELONGATION:
        return None, RejectedBlob(
            centroid, f"not round: {2 * axes[0]:.1f} x {2 * axes[2]:.1f} mm (elongation {elong:.2f}), e.g. clip, rod, "
                      f"streak or bone{_touching_hint(n, voxel_mm3, kit.radius_mm, elong)}", n)
    r0 = float((3.0 * n * voxel_mm3 / (4.0 * np.pi)) ** (1.0 / 3.0))
    lo, hi = _window(volume, ckji, pad_mm=2.5 + 2.0 * float(sp.max()))
    sub = arr[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]].astype(float)
    grid = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), axis=-1).reshape(-1, 3)
    wpts = volume.zyx_to_lps(grid)
    vals = sub.ravel()
    rel0 = wpts - centroid
    dist = np.linalg.norm(rel0, axis=1)
    # window: the ball plus ~2.5 edge sigmas of the slice profile in each direction (thick slices
    # reach further along z), so little of the tissue beyond (skull under the scalp) comes in
    e0 = rel0 / np.maximum(dist, 1e-9)[:, None]
    box_cov = (volume.direction * (sp**2 / 12.0)) @ volume.direction.T
    s_dir = np.sqrt(0.25 + np.einsum("ij,jk,ik->i", e0, box_cov, e0))
    near = dist < r0 + 1.5 + 2.5 * s_dir
    for s in sibs:  # leave out what belongs to a neighbouring blob (touching balls, a clip)
        if np.linalg.norm(s.centroid - centroid) < r0 + s.radius + 6.0:
            near &= np.linalg.norm(wpts - s.centroid, axis=1) - s.radius > dist - r0
    wpts, vals = wpts[near], vals[near]
    if len(vals) < 20:
        return None, RejectedBlob(centroid, "too little around the blob to fit a sphere", n)
    peak = float(np.percentile(vals, 99))
    shell = vals[np.linalg.norm(wpts - centroid, axis=1) > r0 + 1.0]
    b0 = float(np.percentile(shell, 20)) if shell.size else levels["air"]
    x0 = np.r_[centroid, r0 + 0.2, 0.4, peak, b0]
    f_scale = max(3.0 * noise, 0.03 * (peak - b0))
    try:
        params, rms, success = fit_blurred_sphere(wpts, vals, x0, f_scale, box_cov, r_bounds=(max(0.3, 0.4 * r0), 2.5 * r0 + 1.0))
    except (ValueError, np.linalg.LinAlgError):
        return None, RejectedBlob(centroid, "sphere fit failed", n)
    c, r, s_edge, H, b = params[:3], params[3], params[4], params[5], params[6]
    contrast = H - b
    plausible = success and contrast > 0 and np.linalg.norm(c - centroid) < 1.5 and 0.75 * r0 < r < 1.4 * r0 + 0.5
    if not plausible:  # a ball sunk into tissue can throw the one-background fit off: start again from the blob
        rms, success = np.inf, False
    seed = params if plausible else x0
    if (success and contrast > 0) or not plausible:
        surf = refine_on_surface(wpts, vals, seed, f_scale, box_cov, psf_given=True, ball_hu=peak if not plausible else None)
        if surf is not None and surf[1] <= rms * 1.05:
            success = True
            sp_, rms = surf
            # streaks: a final pass with a Cauchy loss (residuals of a few f_scale count far
            # less than with soft-L1) from the converged fit; kept when it stays close
            r_b = (0.95 * sp_[3], 1.05 * sp_[3] + 0.05)
            pol, rms_p, ok_p = (None, rms, False) if rms < 0.5 * f_scale else fit_ball_on_surface(wpts, vals, sp_, f_scale, box_cov, r_bounds=r_b,
                                                   max_tissue_hu=max(sp_[6], sp_[7]) + 0.6 * (sp_[5] - max(sp_[6], sp_[7])), loss="cauchy")
            if ok_p and np.linalg.norm(pol[:3] - sp_[:3]) < 0.3:
                sp_ = pol
            c, r, s_edge, H = sp_[:3], sp_[3], sp_[4], sp_[5]
            contrast = H - min(sp_[6], sp_[7])
    rel = rms / max(contrast, 1.0)
    if not success or contrast <= 0 or H < T:
        return None, RejectedBlob(centroid, "no sphere fits this blob", n, r)
    if rel > MAX_REL_RESIDUAL:
        return None, RejectedBlob(c, f"not a sphere: fit residual {100 * rel:.0f}% of contrast", n, r)
    if kit.density_hu is not None:
        tol = max(300.0, 0.3 * (kit.density_hu - levels["tissue"]))
        if abs(H - kit.density_hu) > tol:
            return None, RejectedBlob(c, f"density {H:.0f} HU, the kit's balls are {kit.density_hu:.0f} HU (e.g. metal)", n, r)
    return dict(c=c, r=float(r), rel=rel, n=n, peak=float(H), elong=elong, s=float(s_edge)), None


def _size_gate(out, candidates, radius_mm) -> None:
    """Keep the candidates whose radius matches ``radius_mm`` (or the median); score them."""
    if radius_mm is not None:
        expected = float(radius_mm)
    else:
        plausible = [d for d in candidates if RADIUS_RANGE_MM[0] <= d["r"] <= RADIUS_RANGE_MM[1]]
        expected = float(np.median([d["r"] for d in plausible])) if plausible else float("nan")
        if plausible:
            out.notes.append(f"radius estimated from the balls: {expected:.2f} mm")
    for d in candidates:
        r = d["r"]
        if not (RADIUS_RANGE_MM[0] <= r <= RADIUS_RANGE_MM[1]) and radius_mm is None:
            out.rejected.append(RejectedBlob(d["c"], f"radius {r:.2f} mm outside the plausible {RADIUS_RANGE_MM[0]}-{RADIUS_RANGE_MM[1]} mm", d["n"], r))
            continue
        dev = abs(r - expected) / expected
        if dev > RADIUS_TOLERANCE:
            what = "expected" if radius_mm is not None else "the other balls have"
            out.rejected.append(RejectedBlob(d["c"], f"wrong size: radius {r:.2f} mm, {what} {expected:.2f} mm", d["n"], r))
            continue
        score = float(np.exp(-d["rel"] / 0.04) * np.exp(-((dev / 0.1) ** 2)) * min(1.0, 1.0 / d["elong"] ** 2))
        out.fiducials.append(Fiducial(d["c"], r, score, d["peak"], d["n"], d["elong"], d["rel"]))


# ---------------------------------------------------------------------------- paper baseline
def detect_fiducials_paper(volume: Volume, threshold_hu: float = 2000.0) -> FiducialDetection:
    """The paper's recipe, as a baseline (Chen et al. 2025, Sec. on CT fiducial detection).

    Fixed grey-value threshold (``threshold_hu``; 2000 HU sits between bone and the balls for a
    typical scanner), statistical outlier removal (drop voxels with fewer than 3 neighbours
    within 1.5 voxel diagonals), DBSCAN in LPS mm (``eps`` 1.5 x the largest spacing,
    ``min_samples`` 4), clusters smaller than 10 voxels dropped, centre = plain centroid of the
    cluster's voxel positions, radius from the cluster's volume. No shape or size check.
    """
    t0 = time.perf_counter()
    out = FiducialDetection(ok=False, reason="", method="paper", threshold_hu=threshold_hu)
    kji, pts = _candidate_points(volume, threshold_hu)
    if len(pts) == 0 or len(pts) > MAX_CANDIDATES:
        out.reason = f"{len(pts)} voxels above {threshold_hu:.0f} HU"
        out.elapsed_s = time.perf_counter() - t0
        return out
    from scipy.spatial import cKDTree

    diag = float(np.linalg.norm(volume.spacing_mm))
    tree = cKDTree(pts)
    counts = np.array([len(x) for x in tree.query_ball_point(pts, 1.5 * diag)]) - 1
    pts = pts[counts >= 3]
    if len(pts) == 0:
        out.reason = "only isolated voxels above the threshold"
        out.elapsed_s = time.perf_counter() - t0
        return out
    labels = DBSCAN(eps=1.5 * float(volume.spacing_mm.max()), min_samples=4).fit_predict(pts)
    voxel_mm3 = float(np.prod(volume.spacing_mm))
    for lab in np.unique(labels[labels >= 0]):
        cp = pts[labels == lab]
        if len(cp) < 10:
            continue
        r = float((3.0 * len(cp) * voxel_mm3 / (4.0 * np.pi)) ** (1.0 / 3.0))
        out.fiducials.append(Fiducial(cp.mean(axis=0), r, 1.0, n_voxels=len(cp)))
    out.fiducials.sort(key=lambda f: -f.centre_lps[2])
    out.ok = bool(out.fiducials)
    out.reason = f"{len(out.fiducials)} clusters" if out.ok else "no clusters"
    out.elapsed_s = time.perf_counter() - t0
    return out
