"""CT fiducial detection benchmark: the product method against the paper's recipe, same run.

Each row is one synthetic scan of the analytic phantom (``monotracker.sim.ct_phantom``); the
truth is the analytic ball centres. Columns: balls found of the phantom's count, false
detections (more than 1 mm from any ball), mean / max centre error (mm) of the found balls,
and detection time (ms, the volume already in memory). Sweeps voxel spacing, grid
orientation, noise, ball radius (given and estimated) and distractors (dense bone nodule,
small bead, metal streaks). The last table times a 512 x 512 x 300 volume (whole head,
0.5 x 0.5 x 1.0 mm, plain and with dental metal; ``--quick``: the metal one at 256 x 256 x 150,
1 x 1 x 2 mm), against the paper's recipe and one threshold pass over the same array (and, with
``--full-grid``, the full-grid ladder the coarse split replaced).

Targets (issue 4): mean error <= 0.05 mm with anisotropic voxels and noise, every ball found
and no false one. Issue 32: the whole head with dental metal (512 x 512 x 300) in at most 5
times one threshold pass over its voxels (``np.count_nonzero(arr > t)``, the floor: every voxel
must be read once), measured in the same run, every ball within 0.1 mm; the timing table prints
that ratio for ours and the paper's recipe, and the last line is JSON.

    PYTHONPATH=app python benchmarks/ct_detection.py [--quick] [--timing-only] [--full-grid]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.distance import cdist

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "app"))

from monotracker.ct.fiducials import detect_fiducials, detect_fiducials_paper
from monotracker.ct.volume import Volume
from monotracker.geometry import rotation_about_axis
from monotracker.sim.ct_phantom import (
    ScanParams,
    default_direction,
    default_distractors,
    generate_ct,
    metal_distractors,
    patch_scan_params,
    with_radius,
)
from monotracker.sim.phantom import default_phantom


def _score(centres: np.ndarray, truth: np.ndarray, tol: float = 1.0):
    if len(centres) == 0:
        return 0, 0, float("nan"), float("nan")
    D = cdist(centres, truth)
    near = D.min(axis=1)
    ok = near <= tol
    found = len(np.unique(D.argmin(axis=1)[ok]))
    err = near[ok]
    return found, int((~ok).sum()), float(err.mean()) if err.size else float("nan"), float(err.max()) if err.size else float("nan")


def _timed(fn, *a, repeat: int = 1, first: bool = False, **kw):
    times = []
    out = None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn(*a, **kw)
        times.append(time.perf_counter() - t)
    return (out, min(times), times[0]) if first else (out, min(times))


def oblique(tilt_deg: float, roll_deg: float, yaw_deg: float = 0.0) -> np.ndarray:
    return (
        rotation_about_axis(np.array([0.0, 0.0, 1.0]), np.radians(yaw_deg))
        @ rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.radians(roll_deg))
        @ rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.radians(tilt_deg))
    )


def cases(quick: bool):
    ph = default_phantom()
    D0 = default_direction()
    out = [
        # (sweep, label, phantom, params, radius given)
        ("spacing", "0.5x0.5x1.0", ph, patch_scan_params(ph), None),
        ("spacing", "0.8x0.8x1.25 (sample)", ph, patch_scan_params(ph, spacing_mm=(0.8, 0.8, 1.25)), None),
        ("spacing", "1.0x1.0x2.0", ph, patch_scan_params(ph, spacing_mm=(1.0, 1.0, 2.0)), None),
        ("noise", "60 HU", ph, patch_scan_params(ph, noise_hu=60.0), None),
        ("distractors", "nodule+bead+streaks", ph, patch_scan_params(ph, metal_streak_hu=2000.0, psf_sigma_mm=0.3, distractors=default_distractors(ph)), None),
        ("radius", "R=2.5 mm (estimated)", with_radius(ph, 2.5), patch_scan_params(with_radius(ph, 2.5)), None),
    ]
    # issue 12: metal denser than the balls, fainter balls, thick slices, embedded balls, streaks
    ph3 = with_radius(ph, 3.0)
    metal = metal_distractors(ph, streak_hu=300.0)
    out += [
        ("metal", "dental+rod, 1500 HU balls", ph, patch_scan_params(ph, spacing_mm=(0.8, 0.8, 1.25), fiducial_hu=1500.0, distractors=metal), None),
        ("thick", "R3 2mm sl. half-emb. streaks", ph3, patch_scan_params(ph3, spacing_mm=(0.5, 0.5, 2.0), fiducial_embed_mm=3.0,
                                                                          distractors=metal_distractors(ph, streak_hu=900.0)), 3.0),
    ]
    if quick:
        return out
    out += [
        ("metal", "dental+rod, 1800 HU balls", ph, patch_scan_params(ph, spacing_mm=(0.8, 0.8, 1.25), fiducial_hu=1800.0, distractors=metal), None),
        ("metal", "dental+rod, 2500 HU balls", ph, patch_scan_params(ph, spacing_mm=(0.8, 0.8, 1.25), fiducial_hu=2500.0, distractors=metal), None),
        ("metal", "dental+rod, 1500 HU, 2 mm", ph, patch_scan_params(ph, spacing_mm=(0.6, 0.6, 2.0), fiducial_hu=1500.0, distractors=metal), None),
        ("thick", "R3 3mm sl. half-emb. streaks", ph3, patch_scan_params(ph3, spacing_mm=(0.5, 0.5, 3.0), fiducial_embed_mm=3.0,
                                                                          distractors=metal_distractors(ph, streak_hu=900.0)), 3.0),
        ("thick", "R3 2mm sl. half-emb. 1500 HU", ph3, patch_scan_params(ph3, spacing_mm=(0.5, 0.5, 2.0), fiducial_embed_mm=3.0,
                                                                          fiducial_hu=1500.0, distractors=metal), 3.0),
        ("embedded", "R4 half-embedded, 1 mm", ph, patch_scan_params(ph, fiducial_embed_mm=4.0), None),
    ]
    out += [
        ("spacing", "0.35x0.35x0.6", ph, patch_scan_params(ph, spacing_mm=(0.35, 0.35, 0.6)), None),
        ("spacing", "0.6x0.6x3.0 (thick)", ph, patch_scan_params(ph, spacing_mm=(0.6, 0.6, 3.0)), None),
        ("orientation", "identity", ph, patch_scan_params(ph, direction=np.eye(3)), None),
        ("orientation", "tilt 30, roll 20, yaw 45", ph, patch_scan_params(ph, direction=oblique(30, 20, 45)), None),
        ("orientation", "flipped axes (det -1)", ph, patch_scan_params(ph, direction=D0 @ np.diag([1.0, -1.0, 1.0])), None),
        ("noise", "0 HU", ph, patch_scan_params(ph, noise_hu=0.0), None),
        ("noise", "30 HU", ph, patch_scan_params(ph, noise_hu=30.0), None),
        ("noise", "100 HU, 1.0x1.0x2.0", ph, patch_scan_params(ph, noise_hu=100.0, spacing_mm=(1.0, 1.0, 2.0)), None),
        ("psf", "PSF 0.8 mm", ph, patch_scan_params(ph, psf_sigma_mm=0.8), None),
        ("radius", "R=1.5 mm, given", with_radius(ph, 1.5), patch_scan_params(with_radius(ph, 1.5), spacing_mm=(0.4, 0.4, 0.8)), 1.5),
        ("radius", "R=3.0 mm, given", with_radius(ph, 3.0), patch_scan_params(with_radius(ph, 3.0)), 3.0),
        ("radius", "R=6.0 mm (estimated)", with_radius(ph, 6.0), patch_scan_params(with_radius(ph, 6.0)), None),
        ("distractors", "nodule+bead, 0.8x0.8x1.25", ph, patch_scan_params(ph, spacing_mm=(0.8, 0.8, 1.25), distractors=default_distractors(ph)), 4.0),
    ]
    return out


def excess_weighted_centroids(vol: Volume, truth: np.ndarray, radius_mm: float, ball_hu: float, tissue_hu: float = 40.0) -> np.ndarray:
    """The centre baseline of issue 12: threshold half way between the ball and soft tissue,
    centroid of the voxels above it weighted by their excess over the threshold, in a sphere of
    ``radius + 2 mm`` around each TRUE centre (seeded by the truth: a generous baseline)."""
    T = 0.5 * (ball_hu + tissue_hu)
    out = []
    for c in truth:
        ijk = vol.lps_to_index(c[None])[0]
        half = np.ceil((radius_mm + 2.5) / vol.spacing_mm).astype(int)
        lo = np.maximum(np.floor(ijk).astype(int) - half, 0)
        hi = np.minimum(np.floor(ijk).astype(int) + half + 1, vol.size_ijk)
        sub = vol.array[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]].astype(float)
        kji = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo[::-1], hi[::-1])], indexing="ij"), -1).reshape(-1, 3)
        p = vol.zyx_to_lps(kji)
        v = sub.ravel()
        w = np.where((v > T) & (np.linalg.norm(p - c, axis=1) < radius_mm + 2.0), v - T, 0.0)
        out.append((p * w[:, None]).sum(axis=0) / max(w.sum(), 1e-9))
    return np.array(out)


def run_sweep(quick: bool) -> list[dict]:
    rows = []
    for sweep, label, ph, params, radius in cases(quick):
        ct = generate_ct(ph, params)
        vol = Volume.from_image(ct.to_sitk(), source=label)
        truth = ct.fiducial_centres_lps
        ours, t_ours = _timed(detect_fiducials, vol, radius_mm=radius, repeat=1 if quick else 2)
        base, t_base = _timed(detect_fiducials_paper, vol, repeat=1 if quick else 2)
        ball_hu = 3000.0 if params.fiducial_hu is None else params.fiducial_hu
        ewc = excess_weighted_centroids(vol, truth, ph.fiducial_radius_mm, ball_hu)
        e_ewc = np.linalg.norm(ewc - truth, axis=1)
        # ours per ball, matched to the truth (inf where missed), against the baseline per ball
        e_ours = cdist(truth, ours.centres).min(axis=1) if len(ours.centres) else np.full(len(truth), np.inf)
        rows.append(dict(sweep=sweep, label=label, n=len(truth), vox=ct.array.size, ours=(*_score(ours.centres, truth), t_ours),
                         base=(*_score(base.centres, truth), t_base), rejected=len(ours.rejected),
                         ewc=(float(e_ewc.mean()), float(e_ewc.max())), worse_than_ewc=int(np.sum(e_ours > e_ewc + 0.005))))
    return rows


def print_sweep(rows):
    hdr = (f"{'sweep':<12} {'case':<28} | {'found':>6} {'false':>5} {'rej':>3} {'mean mm':>8} {'max mm':>7} {'ms':>6} | {'found':>6} {'false':>5} {'mean mm':>8} {'max mm':>7} {'ms':>6}"
           f" | {'mean mm':>8} {'max mm':>7} {'ours>':>5}")
    print(f"{'':<42}| {'robust (ours)':^41} | {'paper baseline (2000 HU)':^37} | {'thr+excess centroid':^23}")
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        o, b, e = r["ours"], r["base"], r["ewc"]
        print(
            f"{r['sweep']:<12} {r['label']:<28} | {o[0]:>3}/{r['n']:<2} {o[1]:>5} {r['rejected']:>3} {o[2]:8.4f} {o[3]:7.4f} {1000 * o[4]:6.0f} | "
            f"{b[0]:>3}/{r['n']:<2} {b[1]:>5} {b[2]:8.4f} {b[3]:7.4f} {1000 * b[4]:6.0f} | {e[0]:8.4f} {e[1]:7.4f} {r['worse_than_ewc']:>5}"
        )
    o = np.array([r["ours"][2] for r in rows])
    b = np.array([r["base"][2] for r in rows])
    ok_all = all(r["ours"][0] == r["n"] and r["ours"][1] == 0 for r in rows)
    print(f"mean of means: ours {np.nanmean(o):.4f} mm, baseline {np.nanmean(b):.4f} mm; ours all found & no false: {ok_all}; "
          f"baseline all found & no false: {all(r['base'][0] == r['n'] and r['base'][1] == 0 for r in rows)}")
    ow = np.array([r["ours"][3] for r in rows])
    print(f"ours across cases: mean {np.nanmean(o):.4f} mm, max {np.nanmax(ow):.4f} mm (target <= 0.04 / 0.10); "
          f"balls where ours is worse than the excess-weighted centroid by > 5 um: {sum(r['worse_than_ewc'] for r in rows)}")


def _full_grid_ladder(vol):
    """The ladder as it was before the coarse split of large components (issue 12): every
    component, the skull included, relabelled on the full grid at each threshold."""
    from monotracker.ct import blob_search

    keep = blob_search.FINE_BOX_MAX
    blob_search.FINE_BOX_MAX = 10**12
    try:
        return detect_fiducials(vol)
    finally:
        blob_search.FINE_BOX_MAX = keep


def threshold_pass_s(arr: np.ndarray, t: float, repeat: int = 5) -> float:
    """The floor of issue 32: one threshold pass over every voxel, ``np.count_nonzero(arr > t)``
    (s, best of ``repeat``): detection must read every voxel at least once."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        np.count_nonzero(arr > t)
        best = min(best, time.perf_counter() - t0)
    return best


def run_timing(quick: bool, full_grid: bool = False, repeat: int | None = None):
    """Whole-head volumes (skull, skin clip; the second with dental fillings, a steel rod and
    1500 HU ceramic balls; ``quick``: the second only, 256 x 256 x 150): ours and the paper's
    recipe against one threshold pass over the same array (the floor), all in this run, each
    timing interleaved with a fresh floor so that a change of load hits both; ``full_grid``:
    also the full-grid ladder the coarse split replaced (slow). Returns the rows as dicts."""
    ph = default_phantom()
    size = (256, 256, 150) if quick else (512, 512, 300)
    sp = (1.0, 1.0, 2.0) if quick else (0.5, 0.5, 1.0)
    repeat = repeat or (1 if quick else 5)
    heads = [] if quick else [("whole head", ScanParams(spacing_mm=sp, size=size, grid_centre_lps=ph.centre_lps + [0, 0, 10.0]))]
    heads.append(("whole head, dental metal, 1500 HU balls",
                  ScanParams(spacing_mm=sp, size=size, grid_centre_lps=ph.centre_lps + [0, 0, 10.0], fiducial_hu=1500.0,
                             distractors=metal_distractors(ph, streak_hu=300.0))))
    out = []
    for label, params in heads:
        t = time.perf_counter()
        ct = generate_ct(ph, params)
        t_gen = time.perf_counter() - t
        vol = Volume.from_image(ct.to_sitk(), source="timing")
        truth = ct.fiducial_centres_lps
        t_thr = float(detect_fiducials(vol).thresholds_hu[0])  # warm-up, and the threshold of the floor
        methods = [("robust (ours)", detect_fiducials), ("paper baseline", detect_fiducials_paper)]
        if full_grid:
            methods.insert(1, ("full-grid ladder (before)", _full_grid_ladder))
        rows = {name: dict(times=[], floors=[], det=None) for name, _ in methods}
        for rep in range(repeat):
            for name, fn in methods:
                if name.startswith("full-grid") and rep:
                    continue
                rows[name]["floors"].append(threshold_pass_s(vol.array, t_thr, 3))
                t = time.perf_counter()
                rows[name]["det"] = fn(vol)
                rows[name]["times"].append(time.perf_counter() - t)
        print(f"\nTiming, {label}: {size[0]}x{size[1]}x{size[2]} voxels ({sp[0]}x{sp[1]}x{sp[2]} mm, oblique, 18 HU noise), "
              f"{os.cpu_count()} CPU cores ({platform.machine()}, load average {os.getloadavg()[0]:.1f}), generated in {t_gen:.1f} s")
        print(f"floor: one threshold pass, np.count_nonzero(arr > {t_thr:.0f}), best of 3 before each run; ratio = time / floor of that run")
        print(f"{'method':<26} {'found':>6} {'false':>5} {'mean mm':>8} {'max mm':>7} {'median s':>9} {'floor s':>8} {'ratio':>6} "
              f"{'best ratio':>10}")
        for name, r in rows.items():
            f, fa, m, mx = _score(r["det"].centres, truth)
            ratios = np.array(r["times"]) / np.array(r["floors"])
            i = int(np.argsort(ratios)[len(ratios) // 2])
            print(f"{name:<26} {f:>3}/{len(truth):<2} {fa:>5} {m:8.4f} {mx:7.4f} {r['times'][i]:9.3f} {r['floors'][i]:8.3f} "
                  f"{ratios[i]:6.2f} {ratios.min():10.2f}")
            out.append(dict(case=label, method=name, found=f, n=len(truth), false=fa, mean_mm=m, max_mm=mx,
                            median_s=r["times"][i], floor_s=r["floors"][i], ratio=float(ratios[i]), best_ratio=float(ratios.min())))
    return out


def run_dicom_geometry() -> None:
    """Series written with pydicom the way scanners write them (true per-pixel positions known),
    loaded by ours and by SimpleITK's plain series reader in the same run; error of 200 known
    points (3D, mm) inside the scanned region, or ours' refusal."""
    import tempfile

    import SimpleITK as sitk

    from monotracker.ct.volume import load_volume
    from monotracker.errors import InputError
    from monotracker.sim.dicom_writer import known_point_errors, stack_specs, tilted_iop, write_series

    rows, cols, ps = 48, 48, (0.8, 0.8)
    rng = np.random.default_rng(12)
    t15 = np.tan(np.radians(15.0))

    def pts_in(z_lo, z_hi, shear=0.0, iop_tilt=0.0):
        p = rng.uniform([6, 6, z_lo], [32, 32, z_hi], size=(200, 3))
        if iop_tilt:  # tilted planes: pixel (c, r) at (c, r cos t, z + r sin t)
            t = np.radians(iop_tilt)
            p = np.column_stack([p[:, 0], p[:, 1] * np.cos(t), p[:, 2] + p[:, 1] * np.sin(t)])
        p[:, 1] += shear * p[:, 2]
        return p

    z = np.arange(30) * 1.25
    gap = lambda n: np.r_[z[:12], z[12 + n:]]
    reversed_specs = stack_specs(z)
    for k, sp in enumerate(reversed_specs):
        sp.instance = len(z) - k
    cases = [
        ("regular 1.25 mm", stack_specs(z), pts_in(1, 35)),
        ("tilt 15 deg, sheared IPP", stack_specs(z, shear_y_per_mm=t15), pts_in(1, 35, shear=t15)),
        ("tilt 15 deg, tilted IOP", stack_specs(z, iop=tilted_iop(15.0)), pts_in(1, 33, iop_tilt=15.0)),
        ("uneven 1.25 then 2.5 mm", stack_specs(np.r_[z[:15], z[14] + 2.5 * np.arange(1, 12)]), pts_in(1, 40)),
        ("1 missing slice", stack_specs(gap(1)), pts_in(1, 35)),
        ("5 missing slices", stack_specs(gap(5)), pts_in(1, 35)),
        ("reversed instance numbers", reversed_specs, pts_in(1, 35)),
    ]

    def plain(folder):
        r = sitk.ImageSeriesReader()
        r.SetFileNames(r.GetGDCMSeriesFileNames(str(folder)))
        return Volume.from_image(r.Execute())

    print("\nDICOM geometry: error of 200 known points after loading (3D, mm), pydicom-written series "
          f"({rows}x{cols} px, {ps[0]} mm pixels), ours vs SimpleITK's plain series reader, same run")
    print(f"{'series':<28} | {'ours mean':>9} {'max':>7}  {'note / refusal':<60} | {'SimpleITK mean':>14} {'max':>7}")
    with tempfile.TemporaryDirectory(prefix="ct-bench-dicom-") as tmp:
        for i, (label, specs, pts) in enumerate(cases):
            def writer(field, tag, i=i, specs=specs):
                folder = Path(tmp) / f"{i}-{tag}-{len(list(Path(tmp).glob(f'{i}-{tag}-*')))}"
                write_series(folder, specs, field, rows, cols, ps)
                return folder

            try:
                def load(folder):
                    v = load_volume(folder)
                    load.notes = v.notes
                    return v
                e = np.linalg.norm(known_point_errors(lambda f: writer(f, "o"), load, specs, pts, rows, cols, ps), axis=1)
                extra = [n for n in load.notes if not n.startswith("DICOM series")]
                ours = f"{e.mean():9.3f} {e.max():7.3f}  {(extra[0] if extra else '-')[:60]:<60}"
            except InputError as exc:
                ours = f"{'refused':>9} {'':>7}  {str(exc).split(': ', 1)[-1][:60]:<60}"
            es = np.linalg.norm(known_point_errors(lambda f: writer(f, "s"), plain, specs, pts, rows, cols, ps), axis=1)
            print(f"{label:<28} | {ours} | {es.mean():14.3f} {es.max():7.3f}")


def run_scan_edges() -> dict:
    """Issue 32 items 1-2 as rows: balls at the corners and edges of resampled series (tilt in
    either encoding, shear, uneven spacing, a gap) must come out within 0.1 mm; balls cut by the
    scan's edge (first / last slice, field of view, reconstruction circle, the slanted face of a
    tilted series, missing slices) must be refused as "cut by the edge of the scan", never given
    a centre. Truth: the balls' LPS positions as written (pydicom series, every pixel at its true
    place) or generated. Prints a table; returns the worst figures."""
    import tempfile
    from dataclasses import replace

    import SimpleITK as sitk

    from monotracker.ct import FiducialKit, load_volume
    from monotracker.sim.ct_phantom import ball_grid_array
    from monotracker.sim.dicom_writer import acquisition_solid, ball_field, points_inset, specs_along, write_series

    R, rows, cols, ps = 3.0, 64, 56, (0.8, 0.7)
    kit = FiducialKit(radius_mm=R)
    X, t15 = np.array([1.0, 0.0, 0.0]), np.radians(15.0)
    uneven = np.r_[np.full(12, 1.0), np.full(14, 1.25)][:, None]
    series = {
        "tilted IOP 15 deg, uneven": (rotation_about_axis(X, t15), uneven * [0, 0, 1.0]),
        "sheared IPP 15 deg, uneven": (np.eye(3), uneven * [0, np.tan(t15), 1.0]),
        "tilted IOP 25 deg about P": (rotation_about_axis(np.array([0, 1.0, 0]), np.radians(25.0)), np.full((30, 3), [0, 0, 1.1])),
        "sheared 8+15 deg, 1 gap": (np.eye(3), np.r_[np.full(10, 1.0), [2.0], np.full(29, 1.0)][:, None]
                                     * [np.tan(np.radians(8.0)), np.tan(t15), 1.0]),
    }
    rows_out = []

    def score(label, det, clear, cut):
        D = cdist(clear, det.centres) if len(det.centres) else np.full((len(clear), 1), np.inf)
        near = D.min(axis=1)
        found = int((near < 1.0).sum())
        err = float(near[near < 1.0].max()) if found else float("nan")
        refused = given = 0
        for c in cut:
            given += int(len(det.centres) and np.linalg.norm(det.centres - c, axis=1).min() < R)
            refused += int(any(np.linalg.norm(r.centre_lps - c) < R + 4.0 and "cut by the edge of the scan" in r.reason
                               for r in det.rejected))
        rows_out.append(dict(case=label, found=found, n=len(clear), max_mm=err, cut=len(cut), refused=refused, given=given))

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ct-bench-edges-") as tmp:
        for i, (label, (rot, steps)) in enumerate(series.items()):
            specs = specs_along(rot, steps)
            balls = np.vstack([points_inset(specs, R + 0.9, rows, cols, ps), points_inset(specs, R + 0.9, rows, cols, ps, "edges")])
            o, E = acquisition_solid(specs, rows, cols, ps)
            write_series(Path(tmp) / f"s{i}", specs, ball_field(balls, R, o + E @ [0.5, 0.5, 0.5]), rows, cols, ps)
            score("corners+edges, " + label, detect_fiducials(load_volume(Path(tmp) / f"s{i}"), kit=kit), balls, np.zeros((0, 3)))
        # the slanted face of a tilted series: half of that ball lies outside every slice
        specs = specs_along(rotation_about_axis(X, np.radians(20.0)), np.full((39, 3), [0, 0, 1.0]))
        o, E = acquisition_solid(specs, rows, cols, ps)
        inside = points_inset(specs, R + 1.0, rows, cols, ps)[[0, 3]]
        face = o + E @ np.array([0.5, 1.0, 0.5])
        write_series(Path(tmp) / "face", specs, ball_field(np.vstack([inside, face]), R, o + E @ [0.5, 0.5, 0.5]), rows, cols, ps)
        score("slanted face, tilted IOP 20 deg", detect_fiducials(load_volume(Path(tmp) / "face"), kit=kit), inside, face[None])
        # two slices missing across a ball
        specs = specs_along(np.eye(3), np.r_[np.full(14, 1.0), [3.0], np.full(14, 1.0)][:, None] * [0, 0, 1.0])
        o, E = acquisition_solid(specs, rows, cols, ps)
        across, clear = np.array([o[0] + 20.0, o[1] + 20.0, 15.5]), np.array([o[0] + 20.0, o[1] + 32.0, 5.0])
        write_series(Path(tmp) / "gap", specs, ball_field([across, clear], R, o + E @ [0.8, 0.8, 0.5]), rows, cols, ps)
        score("2 missing slices across a ball", detect_fiducials(load_volume(Path(tmp) / "gap"), kit=kit), clear[None], across[None])
    inside = np.array([[14.0, 13.0, 20.0]])
    for where, c in (("first slice", [14.0, 13.0, 1.5]), ("last slice", [14.0, 13.0, 38.0]), ("field of view", [28.5, 13.0, 20.0])):
        img = sitk.GetImageFromArray(ball_grid_array(np.vstack([inside, c]), R))
        img.SetSpacing((0.5, 0.5, 1.0))
        score(f"cut by the {where}", detect_fiducials(Volume.from_image(img), kit=kit), inside, np.array([c]))
    # the phantom's grid moved 20 mm along j: the reconstruction circle cuts some balls
    ph = default_phantom()
    p0 = patch_scan_params(ph, margin_mm=8.0, fov_circle=True)
    ct = generate_ct(ph, replace(p0, grid_centre_lps=np.asarray(p0.grid_centre_lps) + np.asarray(p0.direction) @ [0.0, 20.0, 0.0]))
    truth, R4 = ct.fiducial_centres_lps, ph.fiducial_radius_mm
    size, sp = np.array(ct.array.shape[::-1]), ct.spacing_mm
    rel = (truth - ct.origin_mm) @ ct.direction
    circle = max(size[0] * sp[0], size[1] * sp[1]) / 2.0 - np.hypot(rel[:, 0] - (size[0] - 1) / 2.0 * sp[0],
                                                                      rel[:, 1] - (size[1] - 1) / 2.0 * sp[1]) - R4
    box = np.min(np.column_stack([rel, (size - 1) * sp - rel]), axis=1) - R4
    clear, cut = (circle > 1.5) & (box > 1.5), (circle < -1.0) & (box > 1.0)
    score("reconstruction circle (phantom)", detect_fiducials(Volume.from_image(ct.to_sitk()), kit=FiducialKit(radius_mm=R4)),
          truth[clear], truth[cut])
    print(f"\nScan edges (issue 32): balls inside the scan found within 0.1 mm, balls the scan cuts refused "
          f"as 'cut by the edge of the scan' and never given a centre ({time.perf_counter() - t0:.0f} s)")
    print(f"{'case':<48} {'found':>7} {'max mm':>7} {'cut':>4} {'refused':>8} {'centred':>8}")
    for r in rows_out:
        print(f"{r['case']:<48} {r['found']:>3}/{r['n']:<3} {r['max_mm']:7.3f} {r['cut']:>4} {r['refused']:>8} {r['given']:>8}")
    return dict(edges_max_mm=round(max(r["max_mm"] for r in rows_out), 4),
                edges_missed=sum(r["n"] - r["found"] for r in rows_out),
                edges_cut_refused=f"{sum(r['refused'] for r in rows_out)}/{sum(r['cut'] for r in rows_out)}",
                edges_cut_given_a_centre=sum(r["given"] for r in rows_out))


def main(argv=None):
    import json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="few cases and a 256x256x150 timing volume (smoke run)")
    ap.add_argument("--timing-only", action="store_true", help="only the whole-head timing (issue 32's ratio)")
    ap.add_argument("--full-grid", action="store_true", help="also time the full-grid ladder of before the coarse split (slow)")
    ap.add_argument("--repeat", type=int, default=None, help="timed runs per method (default 5, --quick 1)")
    args = ap.parse_args(argv)
    edges = {}
    t = time.perf_counter()
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPU cores at the start")
    if not args.timing_only:
        run_dicom_geometry()
        edges = run_scan_edges()
        print()
        print_sweep(run_sweep(args.quick))
    rows = run_timing(args.quick, args.full_grid, args.repeat)
    print(f"\ntotal {time.perf_counter() - t:.0f} s, load average {os.getloadavg()[0]:.1f} at the end")
    metal = [r for r in rows if "metal" in r["case"]]
    ours = next(r for r in metal if r["method"].startswith("robust"))
    paper = next(r for r in metal if r["method"].startswith("paper"))
    print(json.dumps({"case": ours["case"], "voxels": "256x256x150" if args.quick else "512x512x300",
                      "ours_ratio_to_one_threshold_pass": round(ours["ratio"], 2), "paper_ratio": round(paper["ratio"], 2),
                      "ours_s": round(ours["median_s"], 3), "paper_s": round(paper["median_s"], 3), "floor_s": round(ours["floor_s"], 3),
                      "ours_found": f"{ours['found']}/{ours['n']}", "ours_max_mm": round(ours["max_mm"], 4), "target_ratio": 5.0, **edges}))


if __name__ == "__main__":
    main()
