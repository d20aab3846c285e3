"""Pixels of a checked DICOM series: read (HU, rescale applied slice by slice), stacked, or
resampled onto a regular LPS grid that honours every slice's position
(:mod:`monotracker.ct.dicom_series`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monotracker.ct.coverage import SliceLattice
from monotracker.ct.dicom_geometry import _Geometry
from monotracker.ct.dicom_headers import _read_dataset, _Slice
from monotracker.errors import InputError


def _load_pixels(slices: list[_Slice]) -> None:
    """Read every slice's pixels (HU, float64 only where the rescale needs it). A truncated or
    undecodable slice raises InputError naming it (never dropped)."""
    by_file: dict[Path, list[_Slice]] = {}
    for s in slices:
        by_file.setdefault(s.path, []).append(s)
    for path, group in by_file.items():
        ds = _read_dataset(path, pixels=True)
        if ds is None:
            raise InputError(f"{path.name} has no image data; the series is incomplete")
        hu_applied = False
        try:
            arr = ds.pixel_array
        except Exception as exc:  # noqa: BLE001 - truncated data, unsupported compression
            msg = str(exc).split("\n")[0][:120]
            arr = _decode_compressed(ds, path)  # JPEG & co. without pydicom's optional decoders
            if arr is None:
                raise InputError(f"{path.name} is truncated or its pixel data cannot be decoded ({msg})") from None
            hu_applied = True
        n_frames = int(ds.get("NumberOfFrames", 1) or 1)
        arr = np.asarray(arr)
        if n_frames == 1:
            arr = arr[None]
        if arr.shape[0] != n_frames or arr.shape[1:] != (group[0].rows, group[0].cols):
            raise InputError(f"{path.name} holds pixel data of shape {arr.shape}, not {n_frames} x {group[0].rows} x {group[0].cols}")
        for s in group:
            px = arr[0 if s.frame is None else s.frame]
            if hu_applied:  # GDCM applied the rescale already
                s.pixels = px.astype(np.int32) if px.dtype.kind in "iu" else px.astype(np.float64)
            elif s.slope == 1.0 and float(s.intercept).is_integer():
                s.pixels = px.astype(np.int32) + int(s.intercept)
            else:
                s.pixels = px.astype(np.float64) * s.slope + s.intercept


def _decode_compressed(ds, path: Path):
    """Pixels of a compressed file via SimpleITK/GDCM (HU, rescale applied), or None. Only for
    compressed transfer syntaxes: an uncompressed file pydicom cannot read is damaged, and GDCM
    might pad it silently."""
    meta = getattr(ds, "file_meta", None)
    ts = getattr(meta, "TransferSyntaxUID", None) if meta is not None else None
    if ts is None or not getattr(ts, "is_compressed", False):
        return None
    import SimpleITK as sitk

    try:
        return sitk.GetArrayFromImage(sitk.ReadImage(str(path)))
    except RuntimeError:
        return None


@dataclass
class Stacked:
    """A series' voxels on a regular grid: ``array`` [k, j, i], ``origin`` (LPS mm of voxel 0),
    ``direction`` (3x3, columns = i, j, k axes in LPS), ``spacing`` (i, j, k) mm; ``pad_hu``
    the value given to grid points outside every slice (None: the grid is the slices);
    ``notes`` what the operator should know about the resampling."""

    array: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    spacing: np.ndarray
    pad_hu: float | None = None
    notes: list = field(default_factory=list)
    lattice: SliceLattice | None = None


def _stack(geo: _Geometry) -> Stacked:
    """The volume on its regular grid: the slices as they are (regular series) or resampled."""
    stack = np.stack([s.pixels for s in geo.slices])
    integer = all(s.pixels.dtype.kind in "iu" for s in geo.slices)
    if geo.regular:
        return Stacked(_to_dtype(stack, integer), geo.slices[0].position.copy(),
                       np.column_stack([geo.row, geo.col, geo.normal]), geo.spacing.copy())
    return _resample(geo, stack, integer)


def _to_dtype(a: np.ndarray, integer: bool) -> np.ndarray:
    if integer and a.min() >= -32768 and a.max() <= 32767:
        return a.astype(np.int16) if a.dtype.kind in "iu" else np.rint(a).astype(np.int16)
    return a.astype(np.float32)


#: Tolerance of the grid's extent and of a point's place on a slice, in voxels (positions are
#: decimal strings in DICOM: a slice exactly on the grid's last plane must stay on it).
GRID_TOL = 1e-3


def _slice_corners(geo: _Geometry, H: int, W: int) -> np.ndarray:
    """(4 n, 3) LPS mm: the centres of the four corner pixels of every slice (they bound every
    acquired voxel centre)."""
    sx, sy = geo.spacing[0], geo.spacing[1]
    cu = np.array([0.0, (W - 1) * sx, 0.0, (W - 1) * sx])
    cv = np.array([0.0, 0.0, (H - 1) * sy, (H - 1) * sy])
    pos = geo.positions
    return (pos[:, None, :] + cu[None, :, None] * geo.row + cv[None, :, None] * geo.col).reshape(-1, 3)


def _candidate_frames(geo: _Geometry) -> list[tuple[str, np.ndarray]]:
    """Orthonormal frames (columns ~ row, column, slice axes) the output grid may take: the
    slices' own (row, column, normal), and two that keep the line the slices advance along
    (the table's axis for a tilted gantry) as the third axis, with the row or the column axis."""
    frames = [("the slice axes", np.column_stack([geo.row, geo.col, geo.normal]))]
    pos = geo.positions
    adv = pos[-1] - pos[0]
    if np.linalg.norm(adv) < 1e-6:
        return frames
    s = adv / np.linalg.norm(adv)
    s = s if s @ geo.normal >= 0 else -s
    if 1.0 - abs(s @ geo.normal) < 1e-9:
        return frames
    for keep in ("row", "col"):
        if keep == "row":
            a = geo.row - (geo.row @ s) * s
            a /= np.linalg.norm(a)
            b = np.cross(s, a)
            b = b if b @ geo.col >= 0 else -b
        else:
            b = geo.col - (geo.col @ s) * s
            b /= np.linalg.norm(b)
            a = np.cross(b, s)
            a = a if a @ geo.row >= 0 else -a
        frames.append((f"the table axis (slice positions) and the slice {'rows' if keep == 'row' else 'columns'}",
                       np.column_stack([a, b, s])))
    return frames


def _output_grid(geo: _Geometry, H: int, W: int):
    """The smallest box holding every acquired voxel centre, among :func:`_candidate_frames`:
    ``(name, frame 3x3, lo (3,) in frame coordinates mm, size (ni, nj, nk))``, the spacing
    being the series' own (column, row, slice step)."""
    pts = _slice_corners(geo, H, W)
    best = None
    for name, F in _candidate_frames(geo):
        q = pts @ F
        lo, hi = q.min(axis=0), q.max(axis=0)
        n = np.ceil((hi - lo) / geo.spacing - GRID_TOL).astype(int) + 1
        vol = float(np.prod(n))
        if best is None or vol < best[0] * (1.0 - 1e-3):
            best = (vol, name, F, lo, n)
    return best[1:]


def _largest_correction(geo: _Geometry, H: int, W: int) -> float:
    """Largest distance (mm) between where a voxel was acquired and where a plain stack of the
    slices (first slice's position, slices along the normal at their mean spacing) puts it:
    what resampling corrects, as 3D Slicer's acquisition-geometry regularisation reports."""
    n = len(geo.slices)
    true = _slice_corners(geo, H, W).reshape(n, 4, 3)
    step = (geo.d[-1] - geo.d[0]) / max(n - 1, 1)
    plain = true[:1] + (np.arange(n) * step)[:, None, None] * geo.normal
    return float(np.linalg.norm(true - plain, axis=2).max())


def _resample(geo: _Geometry, stack: np.ndarray, integer: bool) -> Stacked:
    """The box of :func:`_output_grid`, each point interpolated in the acquisition's own
    lattice: linearly between the two slices whose planes bracket it (weight from the distance
    along the normal), both at the same pixel place (the one on the line the slice positions
    advance along: the gantry-tilted scanner's sampling lines; the normal for uneven spacing or
    gaps), bilinearly on each. Exact for a linear field. Grid points up to one grid diagonal
    outside the acquisition extend it (linearly beyond the first and last slice, the edge pixel
    beyond a slice's edge), so that interpolating the grid near the acquisition's faces reads
    acquired data; farther out they get the series' lowest value (``pad_hu``). Where the
    acquisition itself ends is kept in :class:`~monotracker.ct.coverage.SliceLattice`."""
    from scipy.ndimage import map_coordinates

    n, H, W = stack.shape
    name, F, lo, (ni, nj, nk) = _output_grid(geo, H, W)
    if ni * nj * nk > 1_500_000_000 // 8:
        raise InputError(f"resampling this series would need {ni}x{nj}x{nk} voxels; too large")
    sp = geo.spacing
    origin = F @ lo
    fill = float(stack.min())
    stackf = stack.astype(np.float32)
    pos = geo.positions
    out = np.empty((nk, nj, ni), np.float32)
    base = origin + (np.arange(ni) * sp[0])[None, :, None] * F[:, 0] + (np.arange(nj) * sp[1])[:, None, None] * F[:, 1]
    ext = float(np.linalg.norm(sp))  # one grid diagonal, mm
    for k in range(nk):
        P = base + (k * sp[2]) * F[:, 2]
        dp = P @ geo.normal
        kf = np.interp(dp, geo.d, np.arange(n, dtype=float))
        k0 = np.clip(np.floor(kf).astype(int), 0, n - 2)
        # beyond the first / last slice: extrapolate along the stack from the two nearest slices
        w = np.where(dp < geo.d[0], (dp - geo.d[0]) / (geo.d[1] - geo.d[0]),
                     np.where(dp > geo.d[-1], 1.0 + (dp - geo.d[-1]) / (geo.d[-1] - geo.d[-2]), kf - k0))
        wv = w[..., None]
        rel = P - ((1.0 - wv) * pos[k0] + wv * pos[k0 + 1])  # in the plane of the point's own d
        ci = (rel @ geo.row) / sp[0]
        cj = (rel @ geo.col) / sp[1]
        near = ((dp >= geo.d[0] - ext) & (dp <= geo.d[-1] + ext) & (ci >= -ext / sp[0]) & (ci <= W - 1 + ext / sp[0])
                & (cj >= -ext / sp[1]) & (cj <= H - 1 + ext / sp[1]))
        ci, cj = np.clip(ci, 0, W - 1), np.clip(cj, 0, H - 1)
        v0 = map_coordinates(stackf, [k0.astype(float), cj, ci], order=1, mode="nearest")
        v1 = map_coordinates(stackf, [(k0 + 1).astype(float), cj, ci], order=1, mode="nearest")
        out[k] = np.where(near, (1.0 - w) * v0 + w * v1, fill)
    corr = _largest_correction(geo, H, W)
    note = (f"resampled onto a regular grid of {ni} x {nj} x {nk} voxels ({sp[0]:.3g} x {sp[1]:.3g} x {sp[2]:.3g} mm) along "
            f"{name}: the smallest box holding every acquired voxel; largest geometric correction {corr:.2f} mm "
            "(against a plain stack of the slices)")
    lattice = SliceLattice(pos.copy(), geo.d.copy(), geo.row.copy(), geo.col.copy(), geo.normal.copy(),
                           (float(sp[0]), float(sp[1])), H, W)
    return Stacked(_to_dtype(out, integer), origin, F.copy(), sp.copy(), fill, [note], lattice)
