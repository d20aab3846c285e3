"""Dense blobs across a ladder of thresholds: no assumption that the balls are the densest thing.

A single threshold half way between bone and "metal" fails when metal denser than the balls is
in the scan (dental fillings, a steel rod, an aneurysm clip: the threshold lands above 1500-2000
HU ceramic balls and nothing is found). Here the volume is thresholded at a low level first
(a little above soft tissue, or below the kit's density when it is known) and every connected
component (26-connected, on the voxel grid) is handled by size:

* smaller than a ball could be: counted as a speck (noise, streak), not listed one by one;
* ball-sized: handed to ``fit(kji, threshold, siblings)`` (the sphere fit of
  :mod:`.fiducials`); accepted, or rejected with a reason;
* rejected or too large for a ball (skull, a ball touching a streak, two touching balls, metal
  with its halo): the same component is searched again at the next, higher threshold, where it
  may split into parts (two touching balls separate once the threshold passes their contact
  value). Rejections are kept at the lowest level at which the blob is one piece, so a metal
  object is listed once, not once per level.

The ladder is a handful of levels (:data:`LADDER_LEVELS`), so the work is bounded: each level
labels at most the boxes of the components it refines, fits are capped (``max_fits``) and a
time budget stops the search with a note instead of running for minutes on a head full of metal.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from monotracker.ct.volume import Volume

#: Number of thresholds from the lowest level to 85 % of the densest (or the kit's density).
LADDER_LEVELS = 7
_STRUCTURE = np.ones((3, 3, 3), bool)


def threshold_ladder(levels: dict, vmax: float, density_hu: float | None = None) -> np.ndarray:
    """Thresholds (HU, ascending): from ``tissue + max(500, 8 noise)`` (lower when the kit's
    balls are known to be fainter: 45 % of their contrast) up to 85 % of the contrast of the
    kit's density, or of the densest voxel when the density is unknown."""
    tissue, noise = float(levels["tissue"]), float(levels["noise"])
    lo = tissue + max(500.0, 8.0 * noise)
    ref = float(vmax) if density_hu is None else float(density_hu)
    if density_hu is not None:
        lo = max(min(lo, tissue + 0.45 * (ref - tissue)), tissue + 6.0 * noise)
    top = tissue + 0.85 * (ref - tissue)
    if top <= lo + 1.0:
        return np.array([lo])
    return np.linspace(lo, top, LADDER_LEVELS)


@dataclass
class SearchStats:
    specks: int = 0
    fits: int = 0
    components: int = 0
    labelled_voxels: int = 0
    stopped: str = ""
    accepted_at: list = field(default_factory=list)


@dataclass
class Sibling:
    """A neighbouring blob at the same level (LPS centroid, equivalent radius mm): its voxels
    are left out of a blob's fit window."""

    centroid: np.ndarray
    radius: float


def search_blobs(volume: Volume, ladder: np.ndarray, min_voxels: int, max_ball_voxels: int, fit,
                 max_fits: int = 400, time_budget_s: float = 60.0, tissue_hu: float = 0.0, noise_hu: float = 20.0):
    """Run the ladder search (module docstring). ``fit(kji, T, siblings)`` returns
    ``(candidate, None)`` or ``(None, RejectedBlob)``. Returns (candidates, rejected, stats).

    A component whose densest voxel barely passes its threshold (by less than
    ``max(6 noise, 15 % of T - tissue)``) is a fragment of something at about that level (bone
    at a threshold just above it, a streak), not a ball: counted as a speck, not fitted."""
    arr = volume.array
    voxel_mm3 = float(np.prod(volume.spacing_mm))
    t_end = time.perf_counter() + time_budget_s
    cands: list = []
    rejected: list = []
    stats = SearchStats()

    def over_budget() -> bool:
        if stats.stopped:
            return True
        if time.perf_counter() > t_end:
            stats.stopped = f"search stopped after {time_budget_s:.0f} s: results may be incomplete"
        elif stats.fits >= max_fits:
            stats.stopped = f"search stopped after {max_fits} blob fits (a scan full of dense objects?): results may be incomplete"
        return bool(stats.stopped)

    def visit(lo: np.ndarray, hi: np.ndarray, restrict: np.ndarray | None, level: int) -> bool:
        T = float(ladder[level])
        sub = arr[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        mask = sub > T
        if restrict is not None:
            mask &= restrict
        stats.labelled_voxels += mask.size
        labels, n = ndimage.label(mask, structure=_STRUCTURE)
        if n == 0:
            return False
        counts = np.bincount(labels.ravel(), minlength=n + 1)
        stats.components += n
        sizable = np.flatnonzero(counts >= min_voxels)
        sizable = sizable[sizable > 0]
        stats.specks += n - len(sizable)
        if len(sizable) == 0:
            return False
        # a component whose densest voxel barely passes T is a fragment of something at about
        # that level (bone just above a threshold, a streak): counted, not fitted
        on = labels > 0
        peak_of = np.full(n + 1, -np.inf)
        np.maximum.at(peak_of, labels[on], sub[on].astype(float))  # far faster than ndimage.maximum
        peaks = peak_of[sizable]
        small = counts[sizable] <= max_ball_voxels
        faint = small & (peaks < T + max(6.0 * noise_hu, 0.15 * (T - tissue_hu)))
        stats.specks += int(faint.sum())
        todo = sizable[~faint]
        if len(todo) == 0:
            return False
        objs = ndimage.find_objects(labels)
        # blobs that could be (or hold) balls, for the neighbour masks of each other's fits
        idx = [lab for lab in todo if counts[lab] <= 3 * max_ball_voxels]
        comps = {}
        for lab in idx:
            sl = objs[lab - 1]
            comp = labels[sl] == lab
            kji = np.argwhere(comp) + lo + np.array([s.start for s in sl])
            comps[lab] = (sl, comp, kji)
        cents = {lab: volume.zyx_to_lps(kji.mean(axis=0)[None])[0] for lab, (_, _, kji) in comps.items()}
        radii = {lab: float((3.0 * counts[lab] * voxel_mm3 / (4.0 * np.pi)) ** (1.0 / 3.0)) for lab in comps}
        found = False
        for lab in todo:
            c = int(counts[lab])
            if over_budget():
                return found
            sl = objs[lab - 1]
            glo = lo + np.array([s.start for s in sl])
            ghi = lo + np.array([s.stop for s in sl])
            if c > max_ball_voxels:
                comp = labels[sl] == lab
                if level + 1 < len(ladder):
                    found |= visit(glo, ghi, comp, level + 1)
                elif not any(_inside(r.centre_lps, volume, glo, ghi) for r in rejected):
                    kji = np.argwhere(comp) + glo
                    rejected.append(_too_large(volume, kji, c))
                continue
            _, comp, kji = comps[lab]
            sibs = [Sibling(cents[o], radii[o]) for o in comps if o != lab]
            stats.fits += 1
            cand, rej = fit(kji, T, sibs)
            if cand is not None:
                cands.append(cand)
                stats.accepted_at.append(T)
                found = True
                continue
            # not a ball as one piece: it may hold balls that separate at a higher threshold
            n_rej = len(rejected)
            if level + 1 < len(ladder) and visit(glo, ghi, comp, level + 1):
                found = True
                continue
            del rejected[n_rej:]  # the same object seen again higher up: list it once
            rejected.append(rej)
        return found

    shape = np.array(arr.shape)
    visit(np.zeros(3, int), shape, None, 0)
    return cands, rejected, stats


def _inside(p_lps: np.ndarray, volume: Volume, lo: np.ndarray, hi: np.ndarray) -> bool:
    kji = volume.lps_to_index(np.asarray(p_lps)[None])[0][::-1]
    return bool(np.all(kji >= lo - 0.5) and np.all(kji <= hi - 0.5))


def _too_large(volume: Volume, kji: np.ndarray, n: int):
    from monotracker.ct.fiducials import RejectedBlob

    pts = volume.zyx_to_lps(kji[:: max(1, len(kji) // 20000)])
    ext = pts.max(axis=0) - pts.min(axis=0)
    return RejectedBlob(pts.mean(axis=0), f"too large for a fiducial ({ext[0]:.0f} x {ext[1]:.0f} x {ext[2]:.0f} mm, "
                                          f"dense at every threshold): bone, implant or metal", n)
