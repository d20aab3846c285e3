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
Each box is thresholded, labelled and measured (sizes, boxes, densest voxels) by the compiled
:func:`~.label_kernels.threshold_runs` (the same components and numbering as ``ndimage.label``,
no label array: each component as its runs of voxels along i); a component searched again one
level up is restricted to its runs, so only its own voxels are compared there.

**Large volumes** (more than :data:`FINE_BOX_MAX` voxels: a whole head). Labelling a whole
head on the full grid costs ~20 passes over its voxels, so it is never done. One pass builds a
coarse grid (:func:`coarse_grid`: the maximum over blocks of about 2.5 mm, :func:`block_max`),
which also gives the densest value for the ladder. The coarse grid is labelled at the first
level; every coarse piece whose box on the full grid is small (a ball, a clip, a filling) is
searched on the full grid in a crop: its box plus :data:`SIBLING_MARGIN_MM` (so that its
neighbours are there to be left out of its fit), from the first level up, exactly as above, but
only the components whose densest voxel lies in the piece (the others belong to another piece)
and, of those, the ones that run out of the crop (parts of something larger) are searched
higher up without being listed. Every full-grid component above a threshold lies inside exactly
one coarse piece of that threshold (a block is above it when any of its voxels is, and
26-neighbouring voxels lie in 26-neighbouring blocks), so nothing is lost or seen twice.

A large piece (the skull, and what lies within a block or two of it) is refined on a grid of
at most :data:`REFINE_TARGET` blocks (twice the edge for a whole head) at rising thresholds, in steps of a few noise sigmas (and at
every ladder level; ``_LadderSearch._next_level``): some step falls just above the bone's
block maxima, where the bulk of the skull goes and what is denser than bone stands alone.
Small pieces are searched in crops as above, until the ladder ends (what is still large is then
searched on the full grid at the top level). The difference to a full-grid ladder: a ball not
denser than the bone it lies within about two blocks (~5 mm) of, or one standing out from bone
by less than its speck margin (very noisy scans), is found only if that last full-grid search
reaches it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from monotracker.ct.detection_result import RejectedBlob
from monotracker.ct.label_kernels import Runs, block_max_int, threshold_label, threshold_runs
from monotracker.ct.volume import Volume

#: Number of thresholds from the lowest level to 85 % of the densest (or the kit's density).
LADDER_LEVELS = 7
#: Largest box (voxels) searched on the full grid in one piece; larger volumes are split on a
#: coarse grid first (module docstring).
FINE_BOX_MAX = 2_000_000
#: About this many voxels in the coarse grid of a large volume.
COARSE_TARGET = 1_500_000
#: Steps of the thresholds at which large coarse pieces are refined: this many noise sigmas,
#: at least :data:`SUB_STEP_MIN_HU` (see ``_LadderSearch._next_level``).
SUB_STEP_NOISE = 3.0
SUB_STEP_MIN_HU = 50.0
#: Largest grid (voxels) on which large pieces are refined level by level (``refine_large``).
REFINE_TARGET = 200_000
#: A crop reaches this far (mm) beyond its coarse piece: a blob's neighbours within it are left
#: out of its fit window (the fit looks at most ~6 mm beyond a ball's centre).
SIBLING_MARGIN_MM = 6.0
_STRUCTURE = np.ones((3, 3, 3), bool)


def block_size(shape) -> int:
    """Edge (voxels, of a cubic block of as many voxels) of the coarse grid's blocks for a box
    of ``shape``: 1 (no coarse grid) up to :data:`FINE_BOX_MAX` voxels, else about
    ``(voxels / COARSE_TARGET) ** (1/3)``, at least 2."""
    n = float(np.prod(shape))
    if n <= FINE_BOX_MAX:
        return 1
    return max(2, int(round((n / COARSE_TARGET) ** (1.0 / 3.0))))


def _blocks(b: int | tuple, spacing_ijk: np.ndarray) -> tuple:
    """Per-axis block edges (k, j, i) for ``b`` (:func:`block_size`): blocks of about
    ``b**3`` voxels that are as near cubic in mm as the voxels allow (1 x 1 x 2 mm voxels:
    twice as many voxels in-plane as along the slices). A tuple is taken as it is."""
    if isinstance(b, tuple):
        return tuple(int(x) for x in b)
    sp = np.asarray(spacing_ijk, float)[::-1]
    edge = b * float(np.prod(sp)) ** (1.0 / 3.0)
    return tuple(max(1, int(round(edge / s))) for s in sp)


def block_max(arr: np.ndarray, b) -> np.ndarray:
    """Maximum over blocks of ``b`` voxels (an int: cubic; a tuple: per axis k, j, i; the last
    block along an axis may be shorter). Element-wise maxima of strided views: about one pass
    over ``arr`` (a reshape-and-reduce over the short block axes is several times slower)."""
    bb = (int(b),) * 3 if np.isscalar(b) else tuple(int(x) for x in b)
    if arr.dtype.kind in "iu" and arr.ndim == 3:
        return block_max_int(arr, bb)  # compiled: one read (floats keep NumPy's NaN handling)
    out = arr
    for ax, f in enumerate(bb):  # the slowest axis first: later passes read less
        if f <= 1:
            continue
        idx = [slice(None)] * 3
        idx[ax] = slice(0, None, f)
        res = out[tuple(idx)].copy()
        for o in range(1, f):
            idx[ax] = slice(o, None, f)
            part = out[tuple(idx)]
            sl = [slice(None)] * 3
            sl[ax] = slice(0, part.shape[ax])
            np.maximum(res[tuple(sl)], part, out=res[tuple(sl)])
        out = res
    return out


@dataclass
class CoarseGrid:
    """A large volume's coarse grid: ``values`` the maximum over blocks of ``blocks`` voxels
    (k, j, i), and ``vmax`` the volume's densest value (HU)."""

    values: np.ndarray
    blocks: tuple
    vmax: float


def coarse_grid(volume: Volume, block: int | tuple | None = None) -> CoarseGrid | None:
    """The coarse grid of ``volume`` (one pass over its voxels), or None for a volume small
    enough to be searched on the full grid (``block`` None and at most :data:`FINE_BOX_MAX`
    voxels). ``block``: force the blocks (an int edge or a (k, j, i) tuple)."""
    arr = volume.array
    if block is None and arr.size <= FINE_BOX_MAX:
        return None
    b = _blocks(block_size(arr.shape) if block is None else block, volume.spacing_mm)
    values = block_max(arr, b)
    return CoarseGrid(values, b, float(values.max()))


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
    #: Full-grid crops searched for the pieces of a coarse grid.
    crops: int = 0


@dataclass
class Sibling:
    """A neighbouring blob at the same level (LPS centroid, equivalent radius mm): its voxels
    are left out of a blob's fit window."""

    centroid: np.ndarray
    radius: float


@dataclass
class _Crop:
    """A full-grid crop for one coarse piece: the box ``lo``..``hi`` (k, j, i); the piece's
    blocks ``core_blocks`` (bool, coarse grid of ``blocks`` voxels, from coarse index
    ``c_lo``), looked up per voxel by :meth:`in_core`; ``open_lo``/``open_hi`` which faces of
    the box lie inside the scan (a component reaching one runs on outside the crop)."""

    lo: np.ndarray
    hi: np.ndarray
    core_blocks: np.ndarray
    c_lo: np.ndarray
    blocks: tuple
    open_lo: np.ndarray
    open_hi: np.ndarray

    def in_core(self, kji: np.ndarray) -> np.ndarray:
        """Whether the full-grid voxels ``kji`` (n, 3; k, j, i) lie in the piece's blocks (bool
        (n,)): the block of each, looked up (no full-resolution mask of the crop is built)."""
        b = self.core_blocks
        idx = np.asarray(kji) // np.asarray(self.blocks) - self.c_lo
        ok = np.all((idx >= 0) & (idx < np.array(b.shape)), axis=1)
        idx = np.clip(idx, 0, np.array(b.shape) - 1)
        return ok & b[idx[:, 0], idx[:, 1], idx[:, 2]].astype(bool)


class _LadderSearch:
    """The ladder search's state and steps (module docstring); see :func:`search_blobs`."""

    def __init__(self, volume: Volume, ladder, min_voxels: int, max_ball_voxels: int, fit, max_fits: int,
                 time_budget_s: float, tissue_hu: float, noise_hu: float, cancel, describe_large):
        self.volume = volume
        self.arr = volume.array
        self.ladder = np.asarray(ladder, float)
        self.min_voxels, self.max_ball_voxels = int(min_voxels), int(max_ball_voxels)
        self.fit, self.max_fits, self.cancel = fit, int(max_fits), cancel
        self.tissue, self.noise = float(tissue_hu), float(noise_hu)
        self.describe_large = describe_large
        self.voxel_mm3 = float(np.prod(volume.spacing_mm))
        self.t_end = time.perf_counter() + time_budget_s
        self.time_budget_s = time_budget_s
        self.cands: list = []
        self.rejected: list = []
        self.stats = SearchStats()
        self.low = np.asarray(-np.inf if self.arr.dtype.kind == "f" else np.iinfo(self.arr.dtype).min, self.arr.dtype)

    def over_budget(self) -> bool:
        st = self.stats
        if st.stopped:
            return True
        if self.cancel is not None and self.cancel():
            st.stopped = "search cancelled: results incomplete"
        elif time.perf_counter() > self.t_end:
            st.stopped = f"search stopped after {self.time_budget_s:.0f} s: results may be incomplete"
        elif st.fits >= self.max_fits:
            st.stopped = f"search stopped after {self.max_fits} blob fits (a scan full of dense objects?): results may be incomplete"
        return bool(st.stopped)

    def faint(self, peak: float, T: float) -> bool:
        """A component whose densest voxel barely passes ``T``: a fragment of something at about
        that level (bone just above a threshold, a streak), not a ball."""
        return peak < T + max(6.0 * self.noise, 0.15 * (T - self.tissue))

    # ------------------------------------------------------------------ the full grid
    def visit(self, lo: np.ndarray, hi: np.ndarray, restrict: np.ndarray | Runs | None, level: int, crop: _Crop | None = None) -> bool:
        """Search the box ``lo``..``hi`` (restricted to ``restrict``: a mask of the box, or the
        runs of a component found one level down, which are all that is then compared) at
        ``ladder[level]`` and up.
        ``crop``: the box lies in a crop (module docstring): only components whose densest voxel
        is in its core are handled, those running out of it are searched higher up unlisted."""
        arr, ladder, st = self.arr, self.ladder, self.stats
        T = float(ladder[level])
        sub = arr[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        st.labelled_voxels += sub.size
        # the components (26-connected) and their sizes, boxes, densest voxels and runs (no
        # label array: only the voxels above T are read, and only the runs of a component are
        # compared when it is searched again one level up)
        n, counts, box_lo, box_hi, peak, peak_at, runs = threshold_runs(sub, T, restrict)
        if n == 0:
            return False
        st.components += n
        sizable = np.flatnonzero(counts >= self.min_voxels)
        sizable = sizable[sizable > 0]
        st.specks += n - len(sizable)
        if len(sizable) == 0:
            return False

        def box(lab):
            return tuple(slice(int(box_lo[lab, a]), int(box_hi[lab, a])) for a in range(3))

        small = counts[sizable] <= self.max_ball_voxels
        peaks = peak[sizable]
        keep = np.ones(len(sizable), bool)
        running_out = np.zeros(len(sizable), bool)
        if crop is not None:
            keep = crop.in_core(lo + peak_at[sizable])  # the peaks, on the full grid
            glo, ghi = lo + box_lo[sizable], lo + box_hi[sizable]
            running_out = np.any((glo <= crop.lo) & crop.open_lo, axis=1) | np.any((ghi >= crop.hi) & crop.open_hi, axis=1)
        faint = small & (peaks < T + max(6.0 * self.noise, 0.15 * (T - self.tissue)))
        st.specks += int((faint & keep).sum())
        sel = keep & ~faint
        todo = sizable[sel]
        running_out = running_out[sel]
        if len(todo) == 0:
            return False
        # blobs that could be (or hold) balls, for the neighbour masks of each other's fits
        comps = {}
        for lab in sizable[~faint]:
            if counts[lab] > 3 * self.max_ball_voxels:
                continue
            comps[lab] = runs.voxels(lab) + lo
        cents = {lab: self.volume.zyx_to_lps(kji.mean(axis=0)[None])[0] for lab, kji in comps.items()}
        radii = {lab: float((3.0 * counts[lab] * self.voxel_mm3 / (4.0 * np.pi)) ** (1.0 / 3.0)) for lab in comps}
        found = False
        for lab, out_of_crop in zip(todo, running_out):
            c = int(counts[lab])
            if self.over_budget():
                return found
            sl = box(lab)
            glo = lo + np.array([s.start for s in sl])
            ghi = lo + np.array([s.stop for s in sl])
            if out_of_crop:  # part of something larger outside the crop: only what separates higher up
                if level + 1 < len(ladder):
                    found |= self.visit(glo, ghi, runs.runs_in(lab, glo - lo, ghi - lo), level + 1, crop)
                continue
            if c > self.max_ball_voxels:
                if level + 1 < len(ladder):
                    found |= self.visit(glo, ghi, runs.runs_in(lab, glo - lo, ghi - lo), level + 1, crop)
                elif not any(_inside(r.centre_lps, self.volume, glo, ghi) for r in self.rejected):
                    self.rejected.append(self.describe_large(runs.voxels(lab) + lo, c))
                continue
            kji = comps[lab]
            sibs = [Sibling(cents[o], radii[o]) for o in comps if o != lab]
            st.fits += 1
            cand, rej = self.fit(kji, T, sibs)
            if cand is not None:
                self.cands.append(cand)
                st.accepted_at.append(T)
                found = True
                continue
            # not a ball as one piece: it may hold balls that separate at a higher threshold
            n_rej = len(self.rejected)
            if level + 1 < len(ladder) and self.visit(glo, ghi, runs.runs_in(lab, glo - lo, ghi - lo), level + 1, crop):
                found = True
                continue
            del self.rejected[n_rej:]  # the same object seen again higher up: list it once
            self.rejected.append(rej)
        return found

    # ------------------------------------------------------------------ coarse grids
    def crop_visit(self, f_lo: np.ndarray, f_hi: np.ndarray, core_blocks: np.ndarray, c_lo: np.ndarray, blocks: tuple) -> bool:
        """Search, on the full grid from the first level, the crop of one coarse piece: its box
        ``f_lo``..``f_hi`` (full grid) plus :data:`SIBLING_MARGIN_MM`; ``core_blocks`` the
        piece's blocks (coarse grid of ``blocks`` voxels, from coarse index ``c_lo``)."""
        shape = np.array(self.arr.shape)
        # less a hair: spacings that differ in the 7th digit (DICOM's decimal strings against a
        # float header) must give the same crop, hence the same neighbours and the same fits
        margin = np.ceil(SIBLING_MARGIN_MM / self.volume.spacing_mm[::-1] - 1e-6).astype(int)
        lo = np.maximum(f_lo - margin, 0)
        hi = np.minimum(f_hi + margin, shape)
        self.stats.crops += 1
        crop = _Crop(lo, hi, core_blocks, np.asarray(c_lo), tuple(int(x) for x in blocks), lo > 0, hi < shape)
        return self.visit(lo, hi, None, 0, crop)

    def coarse_search(self, grid: CoarseGrid) -> bool:
        """Search a large volume on its coarse grid (module docstring): the first level's
        small pieces in crops, the large ones refined by :meth:`refine_large`."""
        lo, hi = np.zeros(3, int), np.array(self.arr.shape)
        b = grid.blocks
        self.stats.block = max(self.stats.block, max(b))
        values = grid.values
        T = float(self.ladder[0])
        groups, n, counts, g_lo, g_hi, peak, _ = threshold_label(values, T)
        self.stats.labelled_voxels += values.size
        big = np.zeros(values.shape, bool)
        found = False
        for g in range(1, n + 1):
            if self.over_budget():
                return found
            if counts[g] * int(np.prod(b)) < self.min_voxels or self.faint(float(peak[g]), T):
                self.stats.specks += 1
                continue
            sl = tuple(slice(int(g_lo[g, a]), int(g_hi[g, a])) for a in range(3))
            gm = groups[sl] == g
            c_lo = g_lo[g].copy()
            f_lo = lo + c_lo * b
            f_hi = np.minimum(lo + np.array([s.stop for s in sl]) * b, hi)
            if np.prod(f_hi - f_lo) <= FINE_BOX_MAX or len(self.ladder) == 1:
                found |= self.crop_visit(f_lo, f_hi, gm, c_lo, b)
            else:
                big[sl] |= gm
        if big.any():
            found |= self.refine_large(values, b, big, T)
        return found

    def refine_large(self, values: np.ndarray, b: tuple, big: np.ndarray, T: float) -> bool:
        """Large coarse pieces (``big``, on the coarse grid ``values`` of blocks ``b``, above
        ``T``): refined on a grid of at most :data:`REFINE_TARGET` blocks (twice the edge for a
        whole head) at rising thresholds (:meth:`_next_level`)
        until their pieces are small, each searched in a crop; what is still large at the
        ladder's top is searched on the full grid."""
        hi = np.array(self.arr.shape)
        f = (1, 1, 1)  # coarser, by two along every axis, until a level's labelling is cheap
        while np.prod(np.ceil(np.array(values.shape) / f)) > REFINE_TARGET and min(values.shape[a] // f[a] for a in range(3)) > 2:
            f = tuple(2 * x for x in f)
        vals2 = block_max(np.where(big, values, np.asarray(self.low, values.dtype)), f)
        b2 = tuple(b[a] * f[a] for a in range(3))
        self.stats.block = max(self.stats.block, max(b2))
        current = block_max(big, f)
        found = False
        while current.any():
            if self.over_budget():
                return found
            T = self._next_level(T)
            if T > self.ladder[-1] + 1e-6:  # the top: what is still large, on the full grid
                found |= self._full_grid_rest(current, b2)
                break
            # only the box of what is still large is labelled
            # (from the projections onto each axis: np.nonzero would list every block of it)
            ext = [np.flatnonzero(current.any(axis=tuple(x for x in range(3) if x != a))) for a in range(3)]
            blo = np.array([x[0] for x in ext])
            bhi = np.array([x[-1] + 1 for x in ext])
            box = tuple(slice(blo[a], bhi[a]) for a in range(3))
            groups, n, counts, g_lo, g_hi, peak, _ = threshold_label(vals2[box], T, current[box])
            self.stats.labelled_voxels += int(np.prod(bhi - blo))
            nxt = np.zeros_like(current)
            for g in range(1, n + 1):
                if counts[g] * int(np.prod(b2)) < self.min_voxels or self.faint(float(peak[g]), T):
                    self.stats.specks += 1
                    continue
                gm = groups[tuple(slice(int(g_lo[g, a]), int(g_hi[g, a])) for a in range(3))] == g
                c_lo = blo + g_lo[g]
                sl = tuple(slice(int(c_lo[a]), int(c_lo[a] + gm.shape[a])) for a in range(3))
                f_lo = c_lo * b2
                f_hi = np.minimum(np.array([s.stop for s in sl]) * b2, hi)
                if np.prod(f_hi - f_lo) > FINE_BOX_MAX:
                    nxt[sl] |= gm
                    continue
                # the crop's core: the piece's blocks, on the finer grid, of the large pieces only
                # (a coarser block may also hold a small piece already searched)
                k_lo = c_lo * f
                k_hi = np.minimum((c_lo + np.array(gm.shape)) * f, values.shape)
                ix = [np.arange(k_lo[a], k_hi[a]) // f[a] - c_lo[a] for a in range(3)]
                fine = gm[np.ix_(*ix)] & big[k_lo[0]:k_hi[0], k_lo[1]:k_hi[1], k_lo[2]:k_hi[2]]
                if fine.any():
                    found |= self.crop_visit(k_lo * b, np.minimum(k_hi * b, hi), fine, k_lo, b)
            current = nxt
        return found

    def _next_level(self, T: float) -> float:
        """The next threshold for large pieces: the next ladder level, or, sooner, ``T`` plus
        :data:`SUB_STEP_NOISE` noise sigmas (at least :data:`SUB_STEP_MIN_HU`): fine enough that
        some level lies above the bone's block maxima and below a denser ball's peak, less its
        speck margin (bone 1200 HU in 18 HU noise: blocks up to ~1260; a 1500 HU ball: a
        window of ~100 HU), where the ball stands alone on the coarse grid."""
        above = self.ladder[self.ladder > T + 1e-6]
        nxt = float(above[0]) if len(above) else np.inf
        return min(nxt, T + max(SUB_STEP_NOISE * self.noise, SUB_STEP_MIN_HU))

    def _full_grid_rest(self, current: np.ndarray, b2: tuple) -> bool:
        """What is still large at the ladder's top, searched on the full grid at the top level
        (restricted to its blocks): as the full-grid ladder would, slowly (a scan whose balls
        are fainter than the bone they lie near, or a head full of metal)."""
        hi = np.array(self.arr.shape)
        found = False
        groups, _ = ndimage.label(current, structure=_STRUCTURE)
        for g, sl in enumerate(ndimage.find_objects(groups), start=1):
            if sl is None or self.over_budget():
                continue
            gm = groups[sl] == g
            c_lo = np.array([s.start for s in sl])
            f_lo = c_lo * b2
            f_hi = np.minimum(np.array([s.stop for s in sl]) * b2, hi)
            idx = [np.arange(f_lo[a], f_hi[a]) // b2[a] - c_lo[a] for a in range(3)]
            restrict = gm[np.ix_(*[np.clip(ix, 0, gm.shape[a] - 1) for a, ix in enumerate(idx)])]
            found |= self.visit(f_lo, f_hi, restrict, len(self.ladder) - 1)
        return found


def search_blobs(volume: Volume, ladder: np.ndarray, min_voxels: int, max_ball_voxels: int, fit,
                 max_fits: int = 400, time_budget_s: float = 60.0, tissue_hu: float = 0.0, noise_hu: float = 20.0,
                 block: int | tuple | None = None, cancel=None, describe_large=None, grid: CoarseGrid | None = None):
    """Run the ladder search (module docstring). ``fit(kji, T, siblings)`` returns
    ``(candidate, None)`` or ``(None, RejectedBlob)``. Returns (candidates, rejected, stats).
    ``block``: the coarse grid's blocks (an int edge or a (k, j, i) tuple; forces the coarse
    search even on a small volume), None = :func:`block_size`. ``grid``: the volume's coarse
    grid when already built (:func:`coarse_grid`). ``cancel``: a callable; once it returns
    True the search stops (``stats.stopped`` says so). ``describe_large(kji, n) ->
    RejectedBlob``: the rejection of a component too large for a ball at every threshold
    (default :func:`too_large_blob`).

    A component whose densest voxel barely passes its threshold (by less than
    ``max(6 noise, 15 % of T - tissue)``) is a fragment of something at about that level (bone
    at a threshold just above it, a streak), not a ball: counted as a speck, not fitted."""
    if describe_large is None:
        def describe_large(kji, n):
            return too_large_blob(volume, kji, n)

    s = _LadderSearch(volume, ladder, min_voxels, max_ball_voxels, fit, max_fits, time_budget_s, tissue_hu, noise_hu,
                      cancel, describe_large)
    shape = np.array(volume.array.shape)
    if grid is None and block is not None:
        grid = coarse_grid(volume, block)
    if grid is None and volume.array.size > FINE_BOX_MAX:
        grid = coarse_grid(volume)
    if grid is None:
        s.visit(np.zeros(3, int), shape, None, 0)
    else:
        s.coarse_search(grid)
    return s.cands, s.rejected, s.stats


def _inside(p_lps: np.ndarray, volume: Volume, lo: np.ndarray, hi: np.ndarray) -> bool:
    kji = volume.lps_to_index(np.asarray(p_lps)[None])[0][::-1]
    return bool(np.all(kji >= lo - 0.5) and np.all(kji <= hi - 0.5))


def principal_axes(pts: np.ndarray, volume: Volume) -> np.ndarray:
    """Semi-axis lengths (mm, descending) of the solid ellipsoid with the covariance of the
    voxels at ``pts`` (LPS mm). Each voxel counts as its box, not its centre (adds
    ``w**2 / 12`` along each grid axis), so thick slices do not make a ball look flat."""
    if len(pts) < 4:
        return np.zeros(3)
    D, w = volume.direction, volume.spacing_mm
    cov = np.cov(pts.T) + (D * (w**2 / 12.0)) @ D.T
    ev = np.linalg.eigvalsh(cov)[::-1]
    return np.sqrt(np.maximum(5.0 * ev, 0.0))


#: A blob too large for the balls searched for, this round (ratio of its principal axes), is
#: reported as a round ball of another size (the kit's radius is probably wrong).
ROUND_ELONGATION = 1.35


def too_large_blob(volume: Volume, kji: np.ndarray, n: int) -> RejectedBlob:
    """The rejection of a component too large for a ball at every threshold: a round one is
    named a ball of its own radius (``kind`` "round", ``radius_mm`` from its volume) so that a
    wrong kit radius can be told apart from bone, implants or metal."""
    pts = volume.zyx_to_lps(kji[:: max(1, len(kji) // 20000)])
    ext = pts.max(axis=0) - pts.min(axis=0)
    axes = principal_axes(pts, volume)
    if axes[2] > 0 and axes[0] / axes[2] <= ROUND_ELONGATION:
        r_eq = float((3.0 * n * float(np.prod(volume.spacing_mm)) / (4.0 * np.pi)) ** (1.0 / 3.0))
        return RejectedBlob(pts.mean(axis=0), f"round, radius {r_eq:.1f} mm (from its volume): a ball larger than the ones "
                                              "searched for", n, r_eq, kind="round")
    return RejectedBlob(pts.mean(axis=0), f"too large for a fiducial ({ext[0]:.0f} x {ext[1]:.0f} x {ext[2]:.0f} mm, "
                                          f"dense at every threshold): bone, implant or metal", n)
