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
     (clips, wires, streaks, dense bony ridges: ratio of principal axes), then a sub-voxel
     least-squares fit of a blurred sphere ``b + (H - b) * erfc((|x - c| - r) / (sqrt(2) s)) / 2``
     to the raw voxel values in LPS mm (robust ``soft_l1`` loss, so the scalp the ball rests on
     does not pull it). The fit gives the centre, the radius and the residual; balls whose
     radius disagrees with ``radius_mm`` (or, when not given, with the other balls' median) or
     whose residual says "not a sphere" are rejected, with the reason kept.
  4. **Score** in [0, 1] per fiducial: roundness x fit quality x size agreement.

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


def estimate_levels(volume: Volume) -> dict:
    """Grey levels of the scan, HU: ``air``, ``tissue`` (soft-tissue peak), ``noise`` (its
    standard deviation), ``bone`` (98th percentile of voxels denser than tissue + 250 HU),
    ``metal`` (typical value of voxels clearly denser than bone; NaN when there are none)."""
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
    dense = s[s > tissue + 250]
    bone = float(np.percentile(dense, 98)) if dense.size > 50 else tissue + 250.0
    cut = bone + max(300.0, 8.0 * noise)
    cand = arr[arr > cut]
    metal = float(np.percentile(cand, 90)) if cand.size >= 8 else float("nan")
    return {"air": air, "tissue": float(tissue), "noise": noise, "bone": bone, "metal": metal}


# ---------------------------------------------------------------------------- sphere fit
_SQRT2 = np.sqrt(2.0)
_INV_SQRT_PI = 1.0 / np.sqrt(np.pi)


def _sphere_model(params: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    c, r, s, H, b = params[:3], params[3], params[4], params[5], params[6]
    rel = pts - c
    dist = np.sqrt(np.sum(rel * rel, axis=1))
    u = (dist - r) / (_SQRT2 * s)
    fill = 0.5 * erfc(u)
    return b + (H - b) * fill, fill, (dist, rel, u)


def fit_blurred_sphere(pts: np.ndarray, values: np.ndarray, x0: np.ndarray, f_scale: float):
    """Least-squares fit of a blurred ball to voxel values at LPS points ``pts`` (n, 3).

    Parameters ``[cx, cy, cz, r, s, H, b]``: centre and radius (mm), edge sigma (mm), inside
    and background levels (HU). Returns (params, inlier RMS residual HU, success).
    """

    def resid(p):
        m, _, _ = _sphere_model(p, pts)
        return m - values

    def jac(p):
        c, r, s, H, b = p[:3], p[3], p[4], p[5], p[6]
        _, fill, (dist, rel, u) = _sphere_model(p, pts)
        g = -_INV_SQRT_PI * np.exp(-u * u)  # d fill / d u
        du_ddist = 1.0 / (_SQRT2 * s)
        k = (H - b) * g
        J = np.empty((len(pts), 7))
        unit = rel / np.maximum(dist, 1e-9)[:, None]
        J[:, :3] = -(k * du_ddist)[:, None] * unit
        J[:, 3] = -k * du_ddist
        J[:, 4] = -k * u / s
        J[:, 5] = fill
        J[:, 6] = 1.0 - fill
        return J

    lo = np.r_[x0[:3] - 3.0, 0.3, 0.05, -np.inf, -np.inf]
    hi = np.r_[x0[:3] + 3.0, 30.0, 5.0, np.inf, np.inf]
    x0 = np.clip(x0, lo + 1e-6, hi - 1e-6)
    res = least_squares(resid, x0, jac=jac, loss="soft_l1", f_scale=f_scale, bounds=(lo, hi), x_scale="jac", max_nfev=60)
    r = res.fun
    inl = np.abs(r) < 3.0 * f_scale
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("inf")
    return res.x, rms, bool(res.success)


# ---------------------------------------------------------------------------- helpers
def _candidate_points(volume: Volume, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxels above ``threshold``: their (k, j, i) indices and LPS positions."""
    kji = np.argwhere(volume.array > threshold)
    return kji, volume.zyx_to_lps(kji)


def _principal_axes(pts: np.ndarray) -> np.ndarray:
    """Semi-axis lengths (mm, descending) of the solid ellipsoid with the points' covariance."""
    if len(pts) < 4:
        return np.zeros(3)
    ev = np.linalg.eigvalsh(np.cov(pts.T))[::-1]
    return np.sqrt(np.maximum(5.0 * ev, 0.0))


def _window(volume: Volume, kji: np.ndarray, pad_mm: float):
    """Index box around cluster voxels ``kji`` padded by ``pad_mm`` in every direction."""
    pad = np.ceil(pad_mm / volume.spacing_mm[::-1]).astype(int)
    lo = np.maximum(kji.min(axis=0) - pad, 0)
    hi = np.minimum(kji.max(axis=0) + pad + 1, volume.array.shape)
    return lo, hi


# ---------------------------------------------------------------------------- product method
def detect_fiducials(volume: Volume, radius_mm: float | None = None) -> FiducialDetection:
    """Find the sphere fiducials in ``volume`` (see the module docstring).

    ``radius_mm``: the balls' nominal radius; when None it is estimated (each ball's fitted
    radius, checked against the median of all balls). Centres are LPS mm, sub-voxel.
    """
    t0 = time.perf_counter()
    levels = estimate_levels(volume)
    out = FiducialDetection(ok=False, reason="", levels=levels, method="robust")
    bone, metal, noise = levels["bone"], levels["metal"], levels["noise"]
    if not np.isfinite(metal) or metal - bone < max(400.0, 10.0 * noise):
        out.reason = f"no objects denser than bone (bone ~{bone:.0f} HU): no fiducials in this scan"
        out.elapsed_s = time.perf_counter() - t0
        return out
    T = 0.5 * (bone + metal)
    out.threshold_hu = T
    kji, pts = _candidate_points(volume, T)
    if len(pts) > MAX_CANDIDATES:
        out.reason = f"{len(pts)} voxels above {T:.0f} HU: too many for fiducials (metal implant or wrong units?)"
        out.elapsed_s = time.perf_counter() - t0
        return out
    if len(pts) == 0:
        out.reason = "no voxels above the fiducial threshold"
        out.elapsed_s = time.perf_counter() - t0
        return out
    sp = volume.spacing_mm
    eps = 1.01 * float(sp.max())
    labels = DBSCAN(eps=eps, min_samples=1).fit_predict(pts)
    voxel_mm3 = float(np.prod(sp))
    min_vox = max(4, int(np.ceil((4.0 / 3.0) * np.pi * 0.8**3 / voxel_mm3)))
    arr = volume.array

    candidates = []  # (centre, radius, score parts, n, peak, elong)
    for lab in np.unique(labels):
        sel = labels == lab
        cpts, ckji = pts[sel], kji[sel]
        n = int(sel.sum())
        centroid = cpts.mean(axis=0)
        if n < min_vox:
            out.rejected.append(RejectedBlob(centroid, f"too small ({n} voxels): noise or artefact", n))
            continue
        axes = _principal_axes(cpts)
        elong = float(axes[0] / max(axes[2], 1e-6))
        if elong > MAX_ELONGATION:
            out.rejected.append(
                RejectedBlob(centroid, f"not round: {2 * axes[0]:.1f} x {2 * axes[2]:.1f} mm (elongation {elong:.2f}), e.g. clip, wire, streak or bone", n)
            )
            continue
        r0 = float((3.0 * n * voxel_mm3 / (4.0 * np.pi)) ** (1.0 / 3.0))
        lo, hi = _window(volume, ckji, pad_mm=2.5 + 2.0 * float(sp.max()))
        sub = arr[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]].astype(float)
        grid = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), axis=-1).reshape(-1, 3)
        wpts = volume.zyx_to_lps(grid)
        vals = sub.ravel()
        near = np.linalg.norm(wpts - centroid, axis=1) < r0 + 2.0 + 1.5 * float(sp.max())
        wpts, vals = wpts[near], vals[near]
        peak = float(np.percentile(vals, 99))
        shell = vals[np.linalg.norm(wpts - centroid, axis=1) > r0 + 1.0]
        b0 = float(np.percentile(shell, 20)) if shell.size else levels["air"]
        x0 = np.r_[centroid, r0 + 0.2, 0.5, peak, b0]
        f_scale = max(3.0 * noise, 0.03 * (peak - b0))
        try:
            params, rms, success = fit_blurred_sphere(wpts, vals, x0, f_scale)
        except (ValueError, np.linalg.LinAlgError):
            out.rejected.append(RejectedBlob(centroid, "sphere fit failed", n))
            continue
        c, r, s_edge, H, b = params[:3], params[3], params[4], params[5], params[6]
        contrast = H - b
        rel = rms / max(contrast, 1.0)
        if not success or contrast <= 0 or H < T:
            out.rejected.append(RejectedBlob(centroid, "no sphere fits this blob", n, r))
            continue
        if rel > MAX_REL_RESIDUAL:
            out.rejected.append(RejectedBlob(c, f"not a sphere: fit residual {100 * rel:.0f}% of contrast", n, r))
            continue
        candidates.append(dict(c=c, r=float(r), rel=rel, n=n, peak=float(H), elong=elong, s=float(s_edge)))

    # size gate
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

    out.fiducials.sort(key=lambda f: -f.centre_lps[2])
    out.ok = bool(out.fiducials)
    out.reason = (
        f"{len(out.fiducials)} fiducials found" + (f", {len(out.rejected)} dense blobs rejected" if out.rejected else "")
        if out.ok
        else "dense blobs found but none is a sphere of the expected size"
    )
    out.elapsed_s = time.perf_counter() - t0
    return out


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
