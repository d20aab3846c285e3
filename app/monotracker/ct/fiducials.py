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

import numpy as np
from threadpoolctl import ThreadpoolController

from monotracker.ct.blob_search import principal_axes as _principal_axes
from monotracker.ct.blob_search import coarse_grid, search_blobs, threshold_ladder, too_large_blob
from monotracker.ct.coverage import PAD_REACH_MM, blob_touches_border, cut_reason, pad_value
from monotracker.ct.detection_result import Fiducial, FiducialDetection, RejectedBlob
from monotracker.ct.fit_kernels import fit_window
from monotracker.ct.fiducials_paper import MAX_CANDIDATES, detect_fiducials_paper
from monotracker.ct.kit import FiducialKit
from monotracker.ct.levels import _strided_sample, estimate_levels, sample_histogram, soft_tissue_levels
from monotracker.ct.sphere_fit import fit_ball_on_surface, fit_blurred_sphere, refine_on_surface
from monotracker.ct.volume import Volume

__all__ = [
    "MAX_CANDIDATES",
    "Fiducial",
    "FiducialDetection",
    "RejectedBlob",
    "detect_fiducials",
    "detect_fiducials_paper",
    "estimate_levels",
    "fit_ball_on_surface",
    "fit_blurred_sphere",
    "refine_on_surface",
]

#: Bounds of a plausible fiducial radius when none is given, mm.
RADIUS_RANGE_MM = (1.0, 12.0)
#: Largest ratio of the principal axes of a thresholded blob still accepted as a ball.
MAX_ELONGATION = 1.35
#: Largest relative disagreement between a blob's fitted radius and the expected radius.
RADIUS_TOLERANCE = 0.2
#: Largest fit residual (RMS of inliers / contrast) for a sphere.
MAX_REL_RESIDUAL = 0.08


_BLAS: list = []


def _blas_controller() -> ThreadpoolController:
    """The process's thread pools (BLAS, OpenMP), found once: ``threadpool_limits`` looks for
    them on every call (~4 ms of a whole-head detection's ~200)."""
    if not _BLAS:
        _BLAS.append(ThreadpoolController())
    return _BLAS[0]


def _window(volume: Volume, kji: np.ndarray, pad_mm: float):
    """Index box around cluster voxels ``kji`` padded by ``pad_mm`` in every direction."""
    pad = np.ceil(pad_mm / volume.spacing_mm[::-1]).astype(int)
    lo = np.maximum(kji.min(axis=0) - pad, 0)
    hi = np.minimum(kji.max(axis=0) + pad + 1, volume.array.shape)
    return lo, hi


def _box_points(volume: Volume, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """LPS positions (n, 3) mm and values (n,) HU of the voxels of the index box ``lo``..``hi``
    (k, j, i), in C order."""
    sub = volume.array[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]].astype(float)
    grid = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), axis=-1).reshape(-1, 3)
    return volume.zyx_to_lps(grid), sub.ravel()


def _pad_points(volume: Volume, lo: np.ndarray, hi: np.ndarray, pad_hu: float | None):
    """The voxels of the index box ``lo``..``hi`` (k, j, i) whose value is the scan's padding
    ``pad_hu``: LPS positions (n, 3) mm and values (n,), the only ones
    :func:`~.coverage.cut_reason`'s padding check counts; (None, None) when there is no
    padding value (the check is then skipped)."""
    if pad_hu is None:
        return None, None
    sub = volume.array[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    kji = np.argwhere(sub == pad_hu)
    return volume.zyx_to_lps(kji + np.asarray(lo)), np.full(len(kji), float(pad_hu))


def _ball_box(volume: Volume, centre_lps: np.ndarray, reach_mm: float, lo: np.ndarray, hi: np.ndarray):
    """The part of the index box ``lo``..``hi`` (k, j, i) that can hold voxels within
    ``reach_mm`` of ``centre_lps``: the ball's bounding box on the grid (any direction
    matrix), clipped to the box; (lo, hi), possibly empty."""
    inv = np.linalg.inv(volume.direction * volume.spacing_mm[None, :])
    ijk = inv @ (np.asarray(centre_lps, float) - volume.origin_mm)
    ext = reach_mm * np.linalg.norm(inv, axis=1)  # the ball's half extent along i, j, k
    b_lo = np.floor(ijk - ext).astype(int)[::-1]
    b_hi = np.ceil(ijk + ext).astype(int)[::-1] + 1
    return np.maximum(lo, b_lo), np.maximum(np.maximum(lo, b_lo), np.minimum(hi, b_hi))


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
    sample = _strided_sample(volume.array)
    hist, sample_min = sample_histogram(sample)  # one pass over the sample: its levels and its padding
    levels = soft_tissue_levels(sample, hist)
    out = FiducialDetection(ok=False, reason="", levels=levels, method="robust")
    grid = coarse_grid(volume)  # a large volume: one pass, which also gives the densest value
    vmax = grid.vmax if grid is not None else float(np.max(volume.array))
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

    pad_hu = pad_value(volume, sample_min)

    def fit(kji, T, sibs):
        return _fit_blob(volume, kji, T, sibs, levels, kit, pad_hu)

    def describe_large(kji, n):
        """A round blob too large for the kit's balls is fitted for its true radius (a wrong
        kit radius is then named with the scan's; only round ones, so this is rare)."""
        rej = too_large_blob(volume, kji, n)
        if rej.kind == "round":
            cand, _ = _fit_blob(volume, kji, float(ladder[0]), [], levels, FiducialKit(), pad_hu)
            if cand is not None:
                rej = RejectedBlob(cand["c"], f"round ball of radius {cand['r']:.2f} mm: larger than the ones searched for",
                                   n, cand["r"], kind="round")
        return rej

    # The fits solve tiny (n x 11) problems: BLAS threads only add contention (seen: 0.06 s ->
    # 4.5 s of SVD on a loaded 2-core machine), so run them single-threaded.
    with _blas_controller().limit(limits=1, user_api="blas"):
        candidates, rejected, stats = search_blobs(volume, ladder, min_vox, max_vox, fit, time_budget_s=time_budget_s,
                                                    tissue_hu=levels["tissue"], noise_hu=levels["noise"], cancel=cancel,
                                                    describe_large=describe_large, grid=grid)
    out.rejected.extend(rejected)
    _size_gate(out, candidates, radius_mm)
    out.fiducials.sort(key=lambda f: -f.centre_lps[2])
    if stats.specks:
        out.notes.append(f"{stats.specks} small or faint fragments ignored (noise, streaks, bone edges)")
    if stats.stopped:
        out.notes.append(stats.stopped)
    mismatch = _kit_radius_mismatch(out, radius_mm)
    out.ok = bool(out.fiducials)
    out.reason = mismatch or (
        f"{len(out.fiducials)} fiducials found" + (f", {len(out.rejected)} dense blobs rejected" if out.rejected else "")
        if out.ok
        else ("dense blobs found but none is a sphere of the expected size" if out.rejected
              else f"no sphere-shaped blob above {ladder[0]:.0f} HU: no fiducials in this scan")
    )
    if stats.stopped:
        out.reason += " (search stopped early)"
    out.elapsed_s = time.perf_counter() - t0
    return out


def _kit_radius_mismatch(out: FiducialDetection, radius_mm: float | None) -> str:
    """The detection's reason when the scan's balls are of another size than the kit's: at
    least 3 round balls (fitted, or too large to be searched) agree on a radius more than
    :data:`RADIUS_TOLERANCE` off the kit's and outnumber the balls of the kit's size. Those
    few are then not trusted either (fragments of something else at that size, e.g. of a
    clip): moved to ``rejected``. '' when the kit fits (or no radius was given)."""
    if radius_mm is None:
        return ""
    other = [r for r in out.rejected if r.kind in ("round", "wrong_size") and np.isfinite(r.radius_mm)
             and RADIUS_RANGE_MM[0] <= r.radius_mm <= RADIUS_RANGE_MM[1]]
    if len(other) < 3:
        return ""
    med = float(np.median([r.radius_mm for r in other]))
    agree = [r for r in other if abs(r.radius_mm - med) <= 0.15 * med]
    if len(agree) < 3 or len(agree) <= len(out.fiducials) or abs(med - radius_mm) <= RADIUS_TOLERANCE * radius_mm:
        return ""
    for f in out.fiducials:
        out.rejected.append(RejectedBlob(f.centre_lps, f"radius {f.radius_mm:.2f} mm like the kit's, but the scan's "
                                         f"{len(agree)} round balls are {med:.1f} mm: not trusted while the kit's radius is wrong",
                                         f.n_voxels, f.radius_mm))
    out.fiducials = []
    return (f"no fiducials: the kit's radius is {radius_mm:.2g} mm but the scan holds {len(agree)} round balls of radius "
            f"{med:.1f} mm: is the kit's radius right? Set it to {med:.1f} mm, or leave it blank to estimate it")


def _touching_hint(n: int, voxel_mm3: float, radius_mm: float | None, elong: float, minor_mm: float) -> str:
    """A hint that a blob may be 2-4 touching balls: as large as that, elongated like a row of
    balls (1.5-4.5) and as thick as one (smallest semi-axis within 35 % of the radius)."""
    if radius_mm is None or not 1.5 <= elong <= 4.5 or abs(minor_mm - radius_mm) > 0.35 * radius_mm:
        return ""
    k = n * voxel_mm3 / ((4.0 / 3.0) * np.pi * radius_mm**3)
    return f"; as large as {k:.1f} balls: touching balls that could not be separated?" if 1.6 <= k <= 4.5 else ""


def _fit_blob(volume: Volume, ckji: np.ndarray, T: float, sibs, levels: dict, kit: FiducialKit, pad_hu: float | None = None):
    """Edge, shape gate and sphere fit of one blob (voxel indices ``ckji`` (n, 3) k, j, i).
    Returns ``(candidate dict, None)`` or ``(None, RejectedBlob)``. ``sibs``: neighbouring
    blobs whose voxels are kept out of the fit window. ``pad_hu``: the scan's padding value
    (outside the field of view; None: none), for :func:`~.coverage.cut_reason`."""
    sp = volume.spacing_mm
    voxel_mm3 = float(np.prod(sp))
    arr = volume.array
    noise = levels["noise"]
    n = len(ckji)
    cpts = volume.zyx_to_lps(ckji)
    centroid = cpts.mean(axis=0)
    r0 = float((3.0 * n * voxel_mm3 / (4.0 * np.pi)) ** (1.0 / 3.0))
    edge = blob_touches_border(ckji, arr.shape)
    if edge:
        return None, RejectedBlob(centroid, f"cut by the edge of the scan ({edge})", n, kind="cut")
    lo, hi = _window(volume, ckji, pad_mm=2.5 + 2.0 * float(sp.max()))
    # the edge check needs only the window's voxels within reach of the blob's ball: those
    # first, so that a blob refused as not round never has its whole window built
    blo, bhi = _ball_box(volume, centroid, r0 + PAD_REACH_MM, lo, hi)
    cut = cut_reason(volume, centroid, r0, *_pad_points(volume, blo, bhi, pad_hu), pad_hu)
    if cut:
        return None, RejectedBlob(centroid, cut, n, kind="cut")
    axes = _principal_axes(cpts, volume)
    elong = float(axes[0] / max(axes[2], 1e-6))
    if elong > MAX_ELONGATION:
        return None, RejectedBlob(
            centroid, f"not round: {2 * axes[0]:.1f} x {2 * axes[2]:.1f} mm (elongation {elong:.2f}), e.g. clip, rod, "
                      f"streak or bone{_touching_hint(n, voxel_mm3, kit.radius_mm, elong, float(axes[2]))}", n)
    # window: the ball plus ~2.5 edge sigmas of the slice profile in each direction (thick slices
    # reach further along z), so little of the tissue beyond (skull under the scalp) comes in,
    # less what belongs to a neighbouring blob (touching balls, a clip): built in one compiled
    # pass over the box (fit_kernels.fit_window), with the box's padding voxels for the edge
    # check after the fit (the only ones it counts)
    box_cov = (volume.direction * (sp**2 / 12.0)) @ volume.direction.T
    close = [s for s in sibs if np.linalg.norm(s.centroid - centroid) < r0 + s.radius + 6.0]
    sib_c = np.array([s.centroid for s in close], float).reshape(-1, 3)
    sib_r = np.array([s.radius for s in close], float)
    wpts, vals, dist, pad_pts = fit_window(arr[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]], np.asarray(lo, np.int64),
                                           volume.direction * sp[None, :], np.asarray(volume.origin_mm, float),
                                           np.asarray(centroid, float), r0, box_cov, sib_c, sib_r,
                                           0.0 if pad_hu is None else float(pad_hu), pad_hu is not None)
    pad_vals = None if pad_hu is None else np.full(len(pad_pts), float(pad_hu))
    pad_pts = None if pad_hu is None else pad_pts
    if len(vals) < 20:
        return None, RejectedBlob(centroid, "too little around the blob to fit a sphere", n)
    peak = float(np.percentile(vals, 99))
    shell = vals[dist > r0 + 1.0]
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
    cut = cut_reason(volume, c, r, pad_pts, pad_vals, pad_hu)
    if cut:
        return None, RejectedBlob(c, cut, n, r, kind="cut")
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
            out.rejected.append(RejectedBlob(d["c"], f"wrong size: radius {r:.2f} mm, {what} {expected:.2f} mm", d["n"], r,
                                             kind="wrong_size"))
            continue
        score = float(np.exp(-d["rel"] / 0.04) * np.exp(-((dev / 0.1) ** 2)) * min(1.0, 1.0 / d["elong"] ** 2))
        out.fiducials.append(Fiducial(d["c"], r, score, d["peak"], d["n"], d["elong"], d["rel"]))
