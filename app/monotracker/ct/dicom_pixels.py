"""Pixels of a checked DICOM series: read (HU, rescale applied slice by slice), stacked, or
resampled onto a regular LPS grid that honours every slice's position
(:mod:`monotracker.ct.dicom_series`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

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


def _stack(geo: _Geometry) -> tuple[np.ndarray, np.ndarray]:
    """(array [k, j, i], origin LPS mm) of the volume on its regular grid."""
    stack = np.stack([s.pixels for s in geo.slices])
    integer = all(s.pixels.dtype.kind in "iu" for s in geo.slices)
    if geo.regular:
        return _to_dtype(stack, integer), geo.slices[0].position.copy()
    return _resample(geo, stack, integer)


def _to_dtype(a: np.ndarray, integer: bool) -> np.ndarray:
    if integer and a.min() >= -32768 and a.max() <= 32767:
        return np.rint(a).astype(np.int16)
    return a.astype(np.float32)


def _resample(geo: _Geometry, stack: np.ndarray, integer: bool) -> tuple[np.ndarray, np.ndarray]:
    """Regular grid along (row, col, normal) covering every slice's footprint; each output point
    interpolated between the two slices that bracket it, each at the point's own in-plane place."""
    from scipy.ndimage import map_coordinates

    sx, sy, sz = geo.spacing  # column spacing (along row dir), row spacing (along col dir), slice step
    n, H, W = stack.shape
    # footprint of all slices in the (row, col) plane, relative to the first slice's IPP
    u_lo = geo.offsets[:, 0].min()
    u_hi = geo.offsets[:, 0].max() + (W - 1) * sx
    v_lo = geo.offsets[:, 1].min()
    v_hi = geo.offsets[:, 1].max() + (H - 1) * sy
    nu = int(np.floor((u_hi - u_lo) / sx + 1e-6)) + 1
    nv = int(np.floor((v_hi - v_lo) / sy + 1e-6)) + 1
    span = geo.d[-1] - geo.d[0]
    nk = int(np.floor(span / sz + 1e-6)) + 1
    if nu * nv * nk > 1_500_000_000 // 8:
        raise InputError(f"resampling this series would need {nu}x{nv}x{nk} voxels; too large")
    origin = geo.slices[0].position + u_lo * geo.row + v_lo * geo.col
    fill = float(stack.min())
    out = np.empty((nk, nv, nu), np.float32)
    uu = u_lo + np.arange(nu) * sx
    vv = v_lo + np.arange(nv) * sy
    V, U = np.meshgrid(vv, uu, indexing="ij")
    dk = geo.d[0] + np.arange(nk) * sz
    kf = np.interp(dk, geo.d, np.arange(n))
    for k in range(nk):
        k0 = min(int(np.floor(kf[k])), n - 2)
        w = kf[k] - k0
        acc = np.zeros((nv, nu))
        for kk, wk in ((k0, 1.0 - w), (k0 + 1, w)):
            if wk <= 1e-9:
                continue
            ci = (U - geo.offsets[kk, 0]) / sx
            cj = (V - geo.offsets[kk, 1]) / sy
            acc += wk * map_coordinates(stack[kk].astype(np.float64), [cj, ci], order=1, mode="constant", cval=fill)
        out[k] = acc
    return _to_dtype(out, integer), origin
