"""Per-component statistics of a labelled box in one pass (numba), for :mod:`.blob_search`.

``scipy.ndimage`` gives them one at a time (``bincount`` for the sizes, ``find_objects`` for
the boxes, then a pass over each component's box for its densest voxel): three or more passes
over a crop of up to ~2 M voxels per threshold level. :func:`label_stats` reads the labels and
the values once.
"""

from __future__ import annotations

import numpy as np

from monotracker.registration.compiled import compiled


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
                if lab == 0:
                    continue
                v = float(values[k, j, i])
                if counts[lab] == 0:
                    lo[lab, 0], lo[lab, 1], lo[lab, 2] = k, j, i
                    hi[lab, 0], hi[lab, 1], hi[lab, 2] = k + 1, j + 1, i + 1
                    peak[lab] = v
                    pos[lab, 0], pos[lab, 1], pos[lab, 2] = k, j, i
                else:
                    # k only grows in C order; j and i may go either way
                    hi[lab, 0] = k + 1
                    if j < lo[lab, 1]:
                        lo[lab, 1] = j
                    if j + 1 > hi[lab, 1]:
                        hi[lab, 1] = j + 1
                    if i < lo[lab, 2]:
                        lo[lab, 2] = i
                    if i + 1 > hi[lab, 2]:
                        hi[lab, 2] = i + 1
                    if v > peak[lab]:
                        peak[lab] = v
                        pos[lab, 0], pos[lab, 1], pos[lab, 2] = k, j, i
                counts[lab] += 1
    return counts, lo, hi, peak, pos


def label_stats(labels: np.ndarray, values: np.ndarray, n: int):
    """For the components ``1..n`` of ``labels`` (3-D, int, 0 = background) over ``values``
    (same shape, e.g. HU): ``counts`` (n + 1,) voxels (index 0 unused: 0), ``lo``/``hi`` (n + 1, 3)
    the box of each (k, j, i, ``hi`` exclusive, as ``find_objects``), ``peak`` (n + 1,) the
    densest value and ``pos`` (n + 1, 3) its index, the first in C order (as ``np.argmax``)."""
    return _label_stats(labels, values, int(n))


def warm_up() -> None:
    """Compile (or load from numba's cache) :func:`label_stats` for the crops a detection
    passes (int32 labels; int16, float32 and float64 values, views of a larger array)."""
    labels = np.zeros((3, 3, 3), np.int32)
    labels[1, 1, 1] = 1
    for dt in (np.int16, np.float32, np.float64):
        big = np.zeros((4, 4, 4), dt)
        label_stats(labels, big[1:, 1:, 1:], 1)  # a crop (a view)
        label_stats(labels, big[:3].copy(), 1)  # a whole (contiguous) volume
