"""Connected components of a thresholded box and their statistics (numba), for :mod:`.blob_search`.

``scipy.ndimage`` gives them one at a time (a mask, ``label``, ``bincount`` for the sizes,
``find_objects`` for the boxes, then a pass over each component's box for its densest voxel):
five or more passes over a crop of up to ~2 M voxels per threshold level.
:func:`threshold_label` thresholds (NumPy's vectorised compare lists the voxels above), labels
the listed voxels only (26-connected, numbered in the raster order of each component's first
voxel, as ``ndimage.label``: union-find over runs of consecutive voxels along i, so a dense
component costs a union per pair of touching runs, not one per voxel) and measures them;
:func:`label_stats` measures given labels in one. :func:`block_max_int`: the coarse grid of a
large integer volume (:func:`.blob_search.block_max`) in one read of its voxels.
:func:`hist_min_int`: the histogram and minimum of an integer scan's strided sample
(:func:`.levels.sample_histogram`) in one pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monotracker.registration.compiled import compiled, compiled_inline


@compiled_inline
def _add_run(counts, lo, hi, peak, pos, lab, k, j, s, e, best, at):
    """The run of voxels (k, j, s..e-1) into the statistics of component ``lab``, in C order of
    the runs: ``best`` its densest value, at voxel (k, j, at) (the first such in C order)."""
    if counts[lab] == 0:
        lo[lab, 0], lo[lab, 1], lo[lab, 2] = k, j, s
        hi[lab, 0], hi[lab, 1], hi[lab, 2] = k + 1, j + 1, e
        peak[lab] = best
        pos[lab, 0], pos[lab, 1], pos[lab, 2] = k, j, at
    else:
        hi[lab, 0] = k + 1  # k only grows in C order; j and i may go either way
        if j < lo[lab, 1]:
            lo[lab, 1] = j
        if j + 1 > hi[lab, 1]:
            hi[lab, 1] = j + 1
        if s < lo[lab, 2]:
            lo[lab, 2] = s
        if e > hi[lab, 2]:
            hi[lab, 2] = e
        if best > peak[lab]:
            peak[lab] = best
            pos[lab, 0], pos[lab, 1], pos[lab, 2] = k, j, at
    counts[lab] += e - s


@compiled
def _label_stats(labels, values, n):
    counts = np.zeros(n + 1, np.int64)
    lo = np.empty((n + 1, 3), np.int64)
    hi = np.zeros((n + 1, 3), np.int64)
    peak = np.empty(n + 1, np.float64)
    pos = np.zeros((n + 1, 3), np.int64)
    nk, nj, ni = labels.shape
    for k in range(nk):
        for j in range(nj):
            for i in range(ni):
                lab = labels[k, j, i]
                if lab != 0:
                    _add_run(counts, lo, hi, peak, pos, lab, k, j, i, i + 1, float(values[k, j, i]), i)
    return counts, lo, hi, peak, pos


@compiled_inline
def _find(parent, a):
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@compiled
def _label_runs(values, cand, nk, nj, ni, want_labels=True):
    """Label the voxels ``cand`` (flat C-order indices into the (nk, nj, ni) box, ascending:
    the voxels above the threshold, in raster order) 26-connected, and measure the components
    over ``values``. The listed voxels are taken as runs (consecutive voxels of one row k, j)
    and the runs joined by union-find: a run touches a run of one of the four rows visited
    before whose neighbours it can be ((k-1, j-1), (k-1, j), (k-1, j+1), (k, j-1)) when their
    i ranges, one widened by a voxel each side, overlap. A dense component (bone, metal) costs
    a union per pair of touching runs, not per voxel; only the listed voxels are visited.
    ``want_labels`` False: no label array (an empty one; the runs and their labels say it all),
    so nothing of the size of the box is written."""
    # the runs, in raster order of their first voxel: row (k * nj + j), first i, end i (counted
    # first: arrays of the runs' size, not of the voxels')
    n_r = 0
    prev = -2
    for c in cand:
        if c != prev + 1 or c % ni == 0:
            n_r += 1
        prev = c
    run_row = np.empty(n_r, np.int64)
    run_s = np.empty(n_r, np.int64)
    run_e = np.empty(n_r, np.int64)
    n_r = 0
    prev = -2
    row_end = 0
    row = 0
    for c in cand:
        if c >= row_end:  # a new row: divisions once a row, not once a voxel
            row = c // ni
            row_end = (row + 1) * ni
            prev = -2
        if c == prev + 1:
            run_e[n_r - 1] += 1
        else:
            run_row[n_r] = row
            run_s[n_r] = c - row * ni
            run_e[n_r] = c - row * ni + 1
            n_r += 1
        prev = c
    # the runs of each row: row_first[q] .. row_first[q + 1]
    n_rows = nk * nj
    row_first = np.zeros(n_rows + 1, np.int64)
    for r in range(n_r):
        row_first[run_row[r] + 1] += 1
    for q in range(n_rows):
        row_first[q + 1] += row_first[q]
    # union-find over the runs; a set's root is its first run (the smallest index)
    parent = np.arange(n_r)
    ptr = np.empty(4, np.int64)
    stop = np.empty(4, np.int64)
    cur_row = -1
    for r in range(n_r):
        rw = run_row[r]
        if rw != cur_row:  # a new row: a pointer into each neighbouring row's runs
            cur_row = rw
            k = rw // nj
            j = rw - k * nj
            for m in range(4):
                ptr[m] = 0
                stop[m] = 0
            m = 0
            if k > 0:
                for dj in range(-1, 2):
                    jj = j + dj
                    if 0 <= jj < nj:
                        q = rw - nj + dj
                        ptr[m] = row_first[q]
                        stop[m] = row_first[q + 1]
                        m += 1
            if j > 0:
                ptr[m] = row_first[rw - 1]
                stop[m] = row_first[rw]
                m += 1
        s, e = run_s[r], run_e[r]
        root = _find(parent, r)
        for m in range(4):
            t = ptr[m]
            # runs ending before this one's left neighbour touch neither it nor later ones
            while t < stop[m] and run_e[t] < s:
                t += 1
            ptr[m] = t
            while t < stop[m] and run_s[t] <= e:
                o = _find(parent, t)
                if o < root:
                    parent[root] = o
                    root = o
                elif o > root:
                    parent[o] = root
                t += 1
    # numbered in the raster order of each component's first run (its first voxel)
    final = np.zeros(n_r, np.int32)
    m_lab = 0
    for r in range(n_r):
        root = _find(parent, r)
        if root == r:
            m_lab += 1
            final[r] = m_lab
        else:
            final[r] = final[root]
    labels = np.zeros((nk, nj, ni) if want_labels else (0, 0, 0), np.int32)
    counts = np.zeros(m_lab + 1, np.int64)
    lo = np.empty((m_lab + 1, 3), np.int64)
    hi = np.zeros((m_lab + 1, 3), np.int64)
    peak = np.empty(m_lab + 1, np.float64)
    pos = np.zeros((m_lab + 1, 3), np.int64)
    for r in range(n_r):
        lab = final[r]
        rw = run_row[r]
        k = rw // nj
        j = rw - k * nj
        s, e = run_s[r], run_e[r]
        # the densest voxel of the run, the first in C order
        best = float(values[k, j, s])
        at = s
        for i in range(s, e):
            if want_labels:
                labels[k, j, i] = lab
            v = float(values[k, j, i])
            if v > best:
                best = v
                at = i
        _add_run(counts, lo, hi, peak, pos, lab, k, j, s, e, best, at)
    return labels, m_lab, counts, lo, hi, peak, pos, run_row, run_s, run_e, final


@compiled
def _listed_above(values, run_row, run_s, run_e, T):
    """The voxels of the runs (rows ``k * nj + j`` of the box ``values``, i from ``run_s`` to
    ``run_e``, in raster order) whose value is above ``T`` (compared in double precision, as
    NumPy's ``values > np.float64(T)``): flat C-order indices into the box, ascending."""
    nj, ni = values.shape[1], values.shape[2]
    n = 0
    for r in range(run_row.shape[0]):
        n += run_e[r] - run_s[r]
    cand = np.empty(n, np.int64)
    m = 0
    for r in range(run_row.shape[0]):
        rw = run_row[r]
        k = rw // nj
        j = rw - k * nj
        for i in range(run_s[r], run_e[r]):
            if float(values[k, j, i]) > T:
                cand[m] = rw * ni + i
                m += 1
    return cand[:m]


@dataclass(frozen=True)
class Runs:
    """Voxels of a box given as runs along i, in raster order: row ``k * nj + j`` of the box
    (``nj`` its size along j), first i and end i (exclusive), int64 arrays of one length."""

    row: np.ndarray
    start: np.ndarray
    end: np.ndarray

    def crop(self, nj: int, lo, hi) -> "Runs":
        """These runs (of a box ``nj`` voxels along j) in the box ``lo``..``hi`` (k, j, i,
        inside it, holding every voxel of the runs) in its own coordinates; the same order."""
        k, j = np.divmod(self.row, nj)
        return Runs((k - lo[0]) * (hi[1] - lo[1]) + (j - lo[1]), self.start - lo[2], self.end - lo[2])


def _listed(values: np.ndarray, T: float, restrict) -> np.ndarray:
    """The voxels of ``values`` above ``T`` (and in ``restrict``: a mask of the box or its
    :class:`Runs`), flat C-order indices, ascending."""
    if isinstance(restrict, Runs):  # only the voxels of the runs are compared
        return _listed_above(values, restrict.row, restrict.start, restrict.end, np.float64(T))
    # listed by NumPy's vectorised compare (a float64 threshold: the same test as
    # ``value > T`` in double precision for every dtype)
    above = np.greater(values, np.float64(T))
    if restrict is not None:
        above &= np.asarray(restrict, bool)
    return np.flatnonzero(above)


def threshold_label(values: np.ndarray, T: float, restrict: np.ndarray | Runs | None = None):
    """The 26-connected components of ``values > T`` (and ``restrict``, bool of the same shape
    or the :class:`Runs` of the voxels allowed, when given), numbered 1..n in the raster order
    of their first voxel (as ``ndimage.label`` with a full 3 x 3 x 3 structure), and their
    statistics: ``(labels, n, counts, lo, hi, peak, pos)``, the last five as
    :func:`label_stats`."""
    nk, nj, ni = values.shape
    labels, n, counts, lo, hi, peak, pos, _, _, _, _ = _label_runs(values, _listed(values, T, restrict), nk, nj, ni, True)
    return labels, int(n), counts, lo, hi, peak, pos


@dataclass(frozen=True)
class ComponentRuns:
    """The components of a box (``nj`` voxels along j) as runs: ``runs`` ordered by label (each
    component's in raster order), those of label ``lab`` at ``first[lab]:first[lab + 1]``."""

    runs: Runs
    first: np.ndarray
    nj: int

    def _of(self, lab: int) -> Runs:
        a, b = int(self.first[lab]), int(self.first[lab + 1])
        return Runs(self.runs.row[a:b], self.runs.start[a:b], self.runs.end[a:b])

    def runs_in(self, lab: int, lo, hi) -> Runs:
        """The runs of component ``lab`` in the box ``lo``..``hi`` (k, j, i; holding them all,
        e.g. the component's own box) in that box's coordinates."""
        return self._of(lab).crop(self.nj, np.asarray(lo), np.asarray(hi))

    def voxels(self, lab: int) -> np.ndarray:
        """The voxels of component ``lab``, (n, 3) k, j, i in the box, in C order (as
        ``np.argwhere(labels == lab)``)."""
        r = self._of(lab)
        n_run = r.end - r.start
        k, j = np.divmod(r.row, self.nj)
        start = np.cumsum(n_run) - n_run
        i = np.repeat(r.start - start, n_run) + np.arange(int(n_run.sum()))
        return np.column_stack([np.repeat(k, n_run), np.repeat(j, n_run), i])


def threshold_runs(values: np.ndarray, T: float, restrict: np.ndarray | Runs | None = None):
    """:func:`threshold_label` without a label array: ``(n, counts, lo, hi, peak, pos,
    ComponentRuns)``. Nothing of the size of the box is written, only its voxels above ``T``
    read: each component's voxels and runs come from its runs (:class:`ComponentRuns`), and a
    later call restricted to one component (its :meth:`~ComponentRuns.runs_in`) compares only
    those voxels."""
    nk, nj, ni = values.shape
    _, n, counts, lo, hi, peak, pos, row, start, end, lab = _label_runs(values, _listed(values, T, restrict), nk, nj, ni, False)
    order = np.argsort(lab, kind="stable")
    first = np.zeros(int(n) + 2, np.int64)
    first[1:] = np.cumsum(np.bincount(lab, minlength=int(n) + 1))
    return int(n), counts, lo, hi, peak, pos, ComponentRuns(Runs(row[order], start[order], end[order]), first, nj)


def label_stats(labels: np.ndarray, values: np.ndarray, n: int):
    """For the components ``1..n`` of ``labels`` (3-D, int, 0 = background) over ``values``
    (same shape, e.g. HU): ``counts`` (n + 1,) voxels (index 0 unused: 0), ``lo``/``hi`` (n + 1, 3)
    the box of each (k, j, i, ``hi`` exclusive, as ``find_objects``), ``peak`` (n + 1,) the
    densest value and ``pos`` (n + 1, 3) its index, the first in C order (as ``np.argmax``)."""
    return _label_stats(labels, values, int(n))


@compiled
def _block_max(arr, bk, bj, bi):
    nk, nj, ni = arr.shape
    mk, mj, mi = (nk + bk - 1) // bk, (nj + bj - 1) // bj, (ni + bi - 1) // bi
    out = np.empty((mk, mj, mi), arr.dtype)
    buf = np.empty(ni, arr.dtype)
    for ok in range(mk):
        for oj in range(mj):
            k0, j0 = ok * bk, oj * bj
            for i in range(ni):
                buf[i] = arr[k0, j0, i]
            for k in range(k0, min(nk, k0 + bk)):
                for j in range(j0, min(nj, j0 + bj)):
                    for i in range(ni):  # element-wise over a row: vectorised
                        buf[i] = max(buf[i], arr[k, j, i])
            for oi in range(mi):
                i0 = oi * bi
                m = buf[i0]
                for i in range(i0 + 1, min(ni, i0 + bi)):
                    m = max(m, buf[i])
                out[ok, oj, oi] = m
    return out


def block_max_int(arr: np.ndarray, blocks: tuple) -> np.ndarray:
    """Maximum over blocks of ``blocks`` (k, j, i) voxels of an integer array (the last block
    along an axis may be shorter): one read of ``arr``, a row buffer of maxima per block row."""
    return _block_max(arr, int(blocks[0]), int(blocks[1]), int(blocks[2]))


@compiled
def hist_min_int(sample):
    """Counts of the integer values of ``sample`` (3-D, any strides) clipped to -1024..4095
    HU (bin ``v + 1024``), and the smallest value: one pass over the (strided) sample (the grey
    levels' histogram, :func:`.levels.sample_histogram`)."""
    hist = np.zeros(5120, np.int64)
    lo = sample[0, 0, 0]
    nk, nj, ni = sample.shape
    for k in range(nk):
        for j in range(nj):
            for i in range(ni):
                v = sample[k, j, i]
                if v < lo:
                    lo = v
                x = min(max(np.int64(v), -1024), 4095) + 1024
                hist[x] += 1
    return hist, lo


def warm_up() -> None:
    """Compile (or load from numba's cache) :func:`threshold_label` and :func:`label_stats`
    for the crops a detection passes (int32 labels; int16, float32 and float64 values, views of a larger array)."""
    labels = np.zeros((3, 3, 3), np.int32)
    labels[1, 1, 1] = 1
    block_max_int(np.zeros((4, 4, 4), np.int16), (2, 2, 2))  # the coarse grid of an int16 scan
    hist_min_int(np.zeros((8, 8, 8), np.int16)[::2, ::2, ::2])  # an int16 scan's grey levels
    for dt in (np.int16, np.float32, np.float64):
        big = np.zeros((4, 4, 4), dt)
        for vals in (big[1:, 1:, 1:], big[:3].copy()):  # a crop (a view), a whole (contiguous) volume
            label_stats(labels, vals, 1)
            threshold_label(vals, 0.5)
            threshold_label(vals, 0.5, np.ones(vals.shape, bool))
            comps = threshold_runs(vals, -1.0)[-1]  # one component: the whole box
            threshold_runs(vals, 0.5, comps.runs_in(1, (0, 0, 0), vals.shape))
