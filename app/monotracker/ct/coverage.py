"""Where a CT volume holds acquired data, and whether a ball was cut by the edge of the scan.

A ball that the scan's field of view, its first or last slice, or a run of missing slices cuts
has no data on part of its surface: a sphere fit then moves its centre towards the part that
was scanned (1-2 mm with no other sign). Such a ball is refused as a fiducial with the reason
"cut by the edge of the scan" (:func:`cut_reason`), never given a biased centre.

What is not acquired:

* **beyond the grid**: the first and last slice, the in-plane edge of the array;
* **padding**: voxels outside the reconstruction circle (scanners write a constant there, e.g.
  -1024 or -3024 HU) and, in a resampled DICOM series, grid points outside every slice (the
  series' lowest value, :attr:`Coverage.pad_hu`). Padding is recognised by its value: air next
  to a ball (within :data:`PAD_REACH_MM` of its surface) is far brighter than any padding, so
  padding there means the ball crosses into the unscanned region;
* **missing slices**: a slab along the slice normal that a resampled series interpolated
  across (:class:`MissingSlab`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: A ball's surface must lie this far (mm) inside the outermost voxel centres: at least one
#: edge-blur sigma of its profile on every side (see ``tests/ct/test_cut_balls.py`` for the
#: bias measured against this distance).
EDGE_MARGIN_MM = 0.5
#: Padding this close to a ball's surface (mm outside it) means the ball is cut: the blurred
#: edge of a ball over air is still hundreds of HU above air there.
PAD_REACH_MM = 0.5
#: Fewest padding voxels near a ball that mark it as cut (one could be noise at the air floor).
MIN_PAD_VOXELS = 2


@dataclass(frozen=True)
class MissingSlab:
    """Slices missing between two acquired ones, interpolated across on loading: the slab
    ``d_lo < normal . x < d_hi`` (LPS mm, ``normal`` a unit vector) and how many slices."""

    normal: np.ndarray
    d_lo: float
    d_hi: float
    n_missing: int


@dataclass(frozen=True)
class SliceLattice:
    """Where a resampled DICOM series was acquired: its slices (positions ``positions`` (n, 3)
    LPS mm in the order of ``d``, their distances along ``normal``), ``row``/``col`` the in-plane
    axes (unit, LPS), ``pixel_mm`` (along row, along col) and ``rows`` x ``cols`` pixels. A
    point is acquired when it lies between the first and last slice and, on the plane of its
    own distance along the normal (positions interpolated between the bracketing slices), within
    the pixel grid."""

    positions: np.ndarray
    d: np.ndarray
    row: np.ndarray
    col: np.ndarray
    normal: np.ndarray
    pixel_mm: tuple
    rows: int
    cols: int

    def where_outside(self, pts: np.ndarray, margin_mm: float = 0.0) -> str:
        """'' when every point (n, 3) LPS mm is at least ``margin_mm`` inside the acquisition,
        else which edge it crosses: "its first or last slice" or "the edge of the slices"."""
        pts = np.atleast_2d(np.asarray(pts, float))
        dp = pts @ self.normal
        if np.any(dp < self.d[0] + margin_mm) or np.any(dp > self.d[-1] - margin_mm):
            return "its first or last slice"
        n = len(self.d)
        kf = np.interp(dp, self.d, np.arange(n, dtype=float))
        k0 = np.clip(np.floor(kf).astype(int), 0, n - 2)
        w = (kf - k0)[:, None]
        rel = pts - ((1.0 - w) * self.positions[k0] + w * self.positions[k0 + 1])
        u, v = rel @ self.row, rel @ self.col
        if (np.any(u < margin_mm) or np.any(u > (self.cols - 1) * self.pixel_mm[0] - margin_mm)
                or np.any(v < margin_mm) or np.any(v > (self.rows - 1) * self.pixel_mm[1] - margin_mm)):
            return "the edge of the slices (the field of view)"
        return ""


@dataclass
class Coverage:
    """What of a volume's grid holds acquired data (module docstring): ``pad_hu`` the value
    of grid points that were not acquired (None: unknown, the volume's air floor is used),
    ``missing`` slabs of missing slices, ``lattice`` the acquisition of a resampled series
    (None: the grid is the acquisition)."""

    pad_hu: float | None = None
    missing: list = field(default_factory=list)
    lattice: SliceLattice | None = None


def _sphere_points(centre: np.ndarray, radius: float, n: int = 120) -> np.ndarray:
    """``n`` points spread evenly on a sphere (Fibonacci lattice), LPS mm."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5**0.5) * i
    rr = np.sqrt(1.0 - z * z)
    return centre + radius * np.column_stack([rr * np.cos(phi), rr * np.sin(phi), z])


def pad_value(volume, sample_min: float | None) -> float | None:
    """The padding value of ``volume``: its :class:`Coverage`'s, else the lowest value of the
    scan (``sample_min``, e.g. from a strided sample) when it is at or below the air floor
    (-1000 HU); None when there is none."""
    cov = getattr(volume, "coverage", None)
    if cov is not None and cov.pad_hu is not None:
        return float(cov.pad_hu)
    if sample_min is not None and sample_min <= -1000.0:
        return float(sample_min)
    return None


def blob_touches_border(kji: np.ndarray, shape) -> str:
    """'' or which edge of the grid the blob's voxels (k, j, i) reach: the first or last slice,
    or the in-plane edge of the field of view."""
    kji = np.asarray(kji)
    hi = np.asarray(shape) - 1
    if np.any(kji[:, 0] == 0) or np.any(kji[:, 0] == hi[0]):
        return "the first or last slice"
    if np.any(kji[:, 1:] == 0) or np.any(kji[:, 1:] == hi[1:]):
        return "the edge of the field of view"
    return ""


def cut_reason(volume, centre_lps: np.ndarray, radius_mm: float, pts_lps: np.ndarray | None = None,
               values: np.ndarray | None = None, pad_hu: float | None = None) -> str:
    """'' for a ball fully inside the scanned region, else the reason it is refused: "cut by
    the edge of the scan (...)". ``centre_lps`` (3,) mm and ``radius_mm``: the ball (fitted,
    or a blob's centroid and equivalent radius); ``pts_lps`` (n, 3) and ``values`` (n,) the
    voxels around it, for the padding check, with ``pad_hu`` (None: no padding check)."""
    c = np.asarray(centre_lps, float)
    r = float(radius_mm)
    # the grid: the ball plus the margin inside the outermost voxel centres, along each axis
    idx = volume.lps_to_index(c[None])[0]
    reach = (r + EDGE_MARGIN_MM) / volume.spacing_mm
    size = np.array(volume.size_ijk, float)
    out_lo = idx - reach < 0.0
    out_hi = idx + reach > size - 1.0
    if out_lo[2] or out_hi[2]:
        return "cut by the edge of the scan (its first or last slice)"
    if np.any(out_lo[:2] | out_hi[:2]):
        return "cut by the edge of the scan (the edge of the field of view)"
    lattice = getattr(getattr(volume, "coverage", None), "lattice", None)
    if lattice is not None:  # a resampled series: the acquisition is smaller than the grid
        where = lattice.where_outside(_sphere_points(c, r), EDGE_MARGIN_MM)
        if where:
            return f"cut by the edge of the scan ({where})"
    if pad_hu is not None and pts_lps is not None and values is not None:
        near = np.linalg.norm(np.asarray(pts_lps) - c, axis=1) <= r + PAD_REACH_MM
        if int(np.count_nonzero(np.asarray(values)[near] == pad_hu)) >= MIN_PAD_VOXELS:
            return "cut by the edge of the scan (part of it lies outside the reconstructed field of view)"
    for slab in getattr(getattr(volume, "coverage", None), "missing", ()) or ():
        d = float(np.asarray(slab.normal) @ c)
        if d + r + EDGE_MARGIN_MM > slab.d_lo and d - r - EDGE_MARGIN_MM < slab.d_hi:
            return (f"cut by the edge of the scan: {slab.n_missing} of its slices are missing (interpolated across "
                    f"{slab.d_lo:.1f}-{slab.d_hi:.1f} mm along the slice normal)")
    return ""
