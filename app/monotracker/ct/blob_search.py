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

**Large components** (a box of more than :data:`FINE_BOX_MAX` voxels: the skull of a whole
head, a dental arch): relabelling the skull's box on the full grid at every threshold cost seconds
per level on a 512 x 512 x 300 head. The first level is labelled on the full grid, as above (so
every ball apart from bone and metal at that level is found exactly as on a small scan); a large
component is then refined on a coarse grid (the maximum of its voxels over ``b x b x b`` blocks,
``b`` from :func:`block_size`): at each higher level, a coarse piece whose box on the full grid
holds at most ``FINE_BOX_MAX`` voxels goes to the full-resolution search above, from that level
on, restricted to its own voxels; a larger one is split again on the coarse grid one level up,
and searched on the full grid at the last level. Every full-grid component above a threshold
lies inside exactly one coarse piece of that threshold (a block is above it when any of its
voxels is, and 26-neighbouring voxels lie in 26-neighbouring blocks), so nothing is lost or seen
twice; the one difference to a full-grid ladder: inside such a large component, a ball-sized
piece closer than about one block to the rest is first looked at one level higher, once the two
have separated on the coarse grid too (at the last level at full resolution in any case).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from monotracker.ct.volume import Volume

#: Number of thresholds from the lowest level to 85 % of the densest (or the kit's density).
LADDER_LEVELS = 7
#: Largest box (voxels) searched on the full grid in one piece; larger volumes are split on a
#: coarse grid first (module docstring).
FINE_BOX_MAX = 2_000_000
#: About this many voxels in the coarse grid of a large volume.
COARSE_TARGET = 1_500_000
_STRUCTURE = np.ones((3, 3, 3), bool)


def block_size(shape) -> int:
    """Edge (voxels) of the coarse grid's blocks for a box of ``shape``: 1 (no coarse grid) up
    to :data:`FINE_BOX_MAX` voxels, else about ``(voxels / COARSE_TARGET) ** (1/3)``, at least 2."""
    n = float(np.prod(shape))
    if n <= FINE_BOX_MAX:
        return 1
    return max(2, int(round((n / COARSE_TARGET) ** (1.0 / 3.0))))


def block_max(arr: np.ndarray, b: int) -> np.ndarray:
    """Maximum over ``b x b x b`` blocks (the last block along an axis may be shorter)."""
    out = arr
    for ax in range(3):  # the slowest axis first: later passes read less
        n = out.shape[ax]
        m = n // b
        whole = out[(slice(None),) * ax + (slice(0, m * b),)]
        shape = list(whole.shape)
        shape[ax:ax + 1] = [m, b]
        red = whole.reshape(shape).max(axis=ax + 1)  # far faster than np.maximum.reduceat
        if n > m * b:
            rest = out[(slice(None),) * ax + (slice(m * b, n),)].max(axis=ax, keepdims=True)
            red = np.concatenate([red, rest], axis=ax)
        out = red
    return out


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
    #: Largest edge of the coarse grid's blocks used, voxels (1: the full grid only).
    block: int = 1


@dataclass
class Sibling:
    """A neighbouring blob at the same level (LPS centroid, equivalent radius mm): its voxels
    are left out of a blob's fit window."""

    centroid: np.ndarray
    radius: float


def search_blobs(volume: Volume, ladder: np.ndarray, min_voxels: int, max_ball_voxels: int, fit,
                 max_fits: int = 400, time_budget_s: float = 60.0, tissue_hu: float = 0.0, noise_hu: float = 20.0,
                 block: int | None = None, cancel=None):
    """Run the ladder search (module docstring). ``fit(kji, T, siblings)`` returns
    ``(candidate, None)`` or ``(None, RejectedBlob)``. Returns (candidates, rejected, stats).
    ``block``: edge of the coarse grid's blocks for large components (voxels), None =
    :func:`block_size` of the component's box. ``cancel``: a callable; once it returns True
    the search stops (``stats.stopped`` says so).

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
        if cancel is not None and cancel():
            stats.stopped = "search cancelled: results incomplete"
        elif time.perf_counter() > t_end:
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
        # that level (bone just above a threshold, a streak): counted, not fitted. Peaks only of
        # the ball-sized ones, each in its own box (a pass over a whole head's labels is slow)
        objs = ndimage.find_objects(labels)
        small = counts[sizable] <= max_ball_voxels
        peaks = np.full(len(sizable), np.inf)
        for q in np.flatnonzero(small):
            sl = objs[sizable[q] - 1]
            peaks[q] = float(sub[sl][labels[sl] == sizable[q]].max())
        faint = small & (peaks < T + max(6.0 * noise_hu, 0.15 * (T - tissue_hu)))
        stats.specks += int(faint.sum())
        todo = sizable[~faint]
        if len(todo) == 0:
            return False
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
                if level + 1 < len(ladder) and np.prod(ghi - glo) > FINE_BOX_MAX:
                    found |= refine_coarse(glo, ghi, comp, level + 1)
                elif level + 1 < len(ladder):
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

    min_sp = float(np.min(volume.spacing_mm))

    def refine_coarse(lo: np.ndarray, hi: np.ndarray, comp: np.ndarray | None, level: int, exact: bool = False) -> bool:
        """Search the box lo..hi (restricted to the full-grid mask ``comp``, None = all of it)
        from ``level`` on, split on a coarse grid first (module docstring). ``exact``: a
        piece too large for one full-grid box is still searched on the full grid at ``level``
        (the first level), else split again on the coarse grid one level up."""
        b = block_size(hi - lo) if block is None else int(block)
        sub = arr[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        if comp is not None:
            low = np.asarray(-np.inf if sub.dtype.kind == "f" else np.iinfo(sub.dtype).min, sub.dtype)
            sub = np.where(comp, sub, low)
        coarse = block_max(sub, b)
        stats.block = max(stats.block, b)
        # pieces closer than ~6 mm are searched together: they are each other's fit siblings
        grow = int(np.ceil(3.0 / (b * min_sp)))

        def visit_coarse(clo: np.ndarray, chi: np.ndarray, crestrict: np.ndarray | None, level: int) -> bool:
            T = float(ladder[level])
            mask = coarse[clo[0]:chi[0], clo[1]:chi[1], clo[2]:chi[2]] > T
            if crestrict is not None:
                mask &= crestrict
            stats.labelled_voxels += mask.size
            groups, n = ndimage.label(ndimage.binary_dilation(mask, _STRUCTURE, iterations=grow) if grow else mask,
                                      structure=_STRUCTURE)
            found = False
            for g, sl in enumerate(ndimage.find_objects(groups), start=1):
                if sl is None:
                    continue
                if over_budget():
                    return found
                gmask = (groups[sl] == g) & mask[sl]
                nz = np.nonzero(gmask)
                if len(nz[0]) * b**3 < min_voxels:  # cannot hold a blob of min_voxels: a speck
                    stats.specks += 1 if len(nz[0]) else 0
                    continue
                g_lo = np.array([x.min() for x in nz])
                g_hi = np.array([x.max() + 1 for x in nz])
                cmask = gmask[g_lo[0]:g_hi[0], g_lo[1]:g_hi[1], g_lo[2]:g_hi[2]]
                c_lo = clo + np.array([x.start for x in sl]) + g_lo
                c_hi = c_lo + (g_hi - g_lo)
                f_lo, f_hi = c_lo * b, np.minimum(c_hi * b, hi - lo)  # full grid, relative to lo
                if exact or np.prod(f_hi - f_lo) <= FINE_BOX_MAX or level + 1 == len(ladder):
                    idx = [np.arange(f_lo[a], f_hi[a]) // b - c_lo[a] for a in range(3)]
                    restrict = cmask[np.ix_(*idx)]
                    if comp is not None:
                        restrict &= comp[f_lo[0]:f_hi[0], f_lo[1]:f_hi[1], f_lo[2]:f_hi[2]]
                    found |= visit(lo + f_lo, lo + f_hi, restrict, level)
                else:
                    found |= visit_coarse(c_lo, c_hi, cmask, level + 1)
            return found

        return visit_coarse(np.zeros(3, int), np.array(coarse.shape), None, level)

    shape = np.array(arr.shape)
    if arr.size <= FINE_BOX_MAX and block is None:
        visit(np.zeros(3, int), shape, None, 0)
    else:  # a large volume: the first level is split on a coarse grid, each piece searched exactly
        refine_coarse(np.zeros(3, int), shape, None, 0, exact=True)
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
