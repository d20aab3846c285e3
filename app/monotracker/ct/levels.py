"""Grey levels of a CT (air, soft tissue and its noise, bone, metal; HU) from its histogram,
used by the fiducial detection and the head surface."""

from __future__ import annotations

import numpy as np

from monotracker.ct.volume import Volume
from monotracker.ct.label_kernels import hist_min_int


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


#: Integer types counted by the compiled pass (values that ``astype(int32)`` keeps as they are).
_HIST_DTYPES = (np.dtype(np.int8), np.dtype(np.uint8), np.dtype(np.int16), np.dtype(np.uint16), np.dtype(np.int32))


def sample_histogram(sample: np.ndarray) -> tuple[np.ndarray, float]:
    """The histogram :func:`soft_tissue_levels` reads (counts of the values of ``sample``,
    HU, clipped to -1024..4095, bin ``v + 1024``; float) and the sample's smallest value (HU):
    integer samples (a scan's int16) in one compiled pass over the strided view, others by
    NumPy (the same counts)."""
    if sample.dtype in _HIST_DTYPES and sample.ndim == 3 and sample.size:
        hist, lo = hist_min_int(sample)
        return hist.astype(float), float(lo)
    v = np.clip(sample.astype(np.int32, copy=False), -1024, 4095).ravel() + 1024
    return np.bincount(v, minlength=5120).astype(float), float(np.min(sample))


def soft_tissue_levels(sample: np.ndarray, hist: np.ndarray | None = None) -> dict:
    """``air``, ``tissue`` (the soft-tissue peak) and ``noise`` (its standard deviation), HU,
    from a sample of the scan's voxels (:func:`_strided_sample`: about 1.5 M voxels, cheap):
    what the fiducial detection needs. ``hist``: the sample's :func:`sample_histogram` when
    already counted."""
    if hist is None:
        hist = sample_histogram(sample)[0]
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
    return {"air": air, "tissue": float(tissue), "noise": noise}


def estimate_levels(volume: Volume) -> dict:
    """Grey levels of the scan, HU: ``air``, ``tissue`` (soft-tissue peak), ``noise`` (its
    standard deviation) from a sample (:func:`soft_tissue_levels`); ``bone`` (upper bone level)
    and ``metal`` (typical value of the voxels clearly denser than bone; NaN when there are
    none) from every voxel, see the comments inside."""
    arr = volume.array
    soft = soft_tissue_levels(_strided_sample(arr))
    tissue, noise = int(soft["tissue"]), soft["noise"]
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
    return {**soft, "bone": bone, "metal": metal}
