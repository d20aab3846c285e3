"""DICOM series read slice by slice with pydicom: geometry that is right or refused.

A scanner writes each slice with its own ImagePositionPatient (IPP) and ImageOrientationPatient
(IOP). A plain series reader assumes they form a regular box (positions along the slice normal,
one spacing), which is silently wrong for gantry-tilted series (either encoding: a tilted IOP with
positions along the table, or an axial IOP with positions sheared along y), uneven spacing and
missing slices. Here every slice's real geometry is read and checked:

* **Regular** (positions along the normal, one spacing within 1 % + 0.01 mm): the slices are
  stacked as they are; direction = (row, column, normal), origin = first slice's IPP.
* **Known but irregular** (tilt, uneven spacing, a gap of at most :data:`MAX_MISSING_SLICES`
  missing slices): resampled onto a regular LPS grid (row, column, normal axes) that honours every
  slice's real position, like 3D Slicer's acquisition-geometry regularisation: an output point
  is interpolated linearly between the two slices whose planes bracket it, each sampled
  bilinearly at the point's own in-plane position on that slice. A note says so.
* **Not known** (mixed orientations or pixel grids, a larger gap, two slices at one position
  with different content, two acquisitions interleaved under one series UID, a corrupt or
  truncated slice): :class:`~monotracker.errors.InputError` with one line naming the problem.

Enhanced (multi-frame) CT objects are read frame by frame from their functional groups.
Positions are LPS mm (DICOM's patient frame). Pixel values are HU (rescale slope/intercept).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monotracker.ct.dicom_interleave import check_interleaved
from monotracker.errors import InputError

log = logging.getLogger(__name__)

#: Largest number of consecutive missing slices interpolated across; a larger gap is refused.
MAX_MISSING_SLICES = 2
#: Relative spread of slice gaps still read as one uniform spacing.
SPACING_RTOL = 0.01
#: Absolute tolerance on positions (mm): DICOM writes IPP as decimal strings.
POS_ATOL_MM = 0.01
#: Largest difference between two slices' direction cosines still read as one orientation.
IOP_ATOL = 1e-3


@dataclass
class SeriesInfo:
    """One DICOM series of a folder: what the operator needs to choose it.

    ``spacing_mm`` is (column, row, slice) spacing in mm (slice = median gap along the normal);
    ``tilt_deg`` the angle between the slice normal and the line through the slice positions
    (0 for a regular series); ``notes`` what loading it would say (resampling) or the one-line
    reason it would be refused (``ok`` False).
    """

    uid: str
    description: str
    slices: int
    spacing_mm: tuple[float, float, float]
    tilt_deg: float
    notes: list[str] = field(default_factory=list)
    ok: bool = True
    modality: str = ""
    files: list[str] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict:
        return {
            "uid": self.uid,
            "description": self.description,
            "modality": self.modality,
            "slices": self.slices,
            "spacing_mm": [round(float(s), 4) for s in self.spacing_mm],
            "tilt_deg": round(float(self.tilt_deg), 2),
            "ok": self.ok,
            "notes": list(self.notes),
        }


@dataclass
class _Slice:
    """One 2D image (a single-frame file or one frame of a multi-frame file)."""

    path: Path
    frame: int | None
    position: np.ndarray  # IPP, LPS mm
    iop: np.ndarray  # 6 direction cosines: row (along columns index i), column (along j)
    pixel_spacing: tuple[float, float]  # (between rows, between columns) mm, DICOM order
    rows: int
    cols: int
    slope: float
    intercept: float
    instance: int
    acquisition: str
    pixels: np.ndarray | None = None
    #: AcquisitionTime (else ContentTime) of the slice, s since midnight; None when absent.
    time_s: float | None = None


# ---------------------------------------------------------------------------- reading headers
def _pydicom():
    try:
        import pydicom
    except ImportError as exc:  # pragma: no cover - a main dependency
        raise InputError(f"pydicom is not installed ({exc}); reinstall MonoTracker") from None
    return pydicom


def _floats(v, n: int, what: str, path: Path) -> np.ndarray:
    try:
        a = np.array([float(x) for x in v], float)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise InputError(f"{path.name}: {what} is missing or malformed; its geometry cannot be trusted")
    return a


def _looks_like_dicom(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            head = fh.read(132)
    except OSError:
        return False
    return head[128:132] == b"DICM" or path.suffix.lower() in (".dcm", ".dicom", ".ima")


def _read_dataset(path: Path, pixels: bool):
    """pydicom dataset, None for a file that is not a DICOM image; InputError for a damaged one."""
    pydicom = _pydicom()
    try:
        ds = pydicom.dcmread(str(path), stop_before_pixels=not pixels)
    except PermissionError:
        raise InputError(f"cannot read {path}: permission denied") from None
    except pydicom.errors.InvalidDicomError:
        if _looks_like_dicom(path):
            raise InputError(f"{path.name} is a damaged DICOM file (unreadable header)") from None
        return None
    except Exception as exc:  # noqa: BLE001 - pydicom raises many kinds on a damaged file
        if _looks_like_dicom(path):
            raise InputError(f"{path.name} is a truncated or corrupt DICOM file ({type(exc).__name__})") from None
        return None
    if "SeriesInstanceUID" not in ds:
        meta = getattr(ds, "file_meta", None)
        if "SOPClassUID" not in ds and (meta is None or "MediaStorageSOPClassUID" not in meta) and _looks_like_dicom(path):
            raise InputError(f"{path.name} is a damaged DICOM file (no readable header)")
        return None
    if pixels:
        if "PixelData" not in ds:
            return None
    elif "Rows" not in ds:  # DICOMDIR, structured reports, RT structures...
        return None
    return ds


def _seq_item(ds, seq_name: str, attr: str):
    seq = ds.get(seq_name)
    if seq:
        return seq[0].get(attr)
    return None


def _frame_attr(ds, frame_item, seq_name: str, attr: str):
    """Attribute of a functional group: per-frame first, then shared."""
    if frame_item is not None and seq_name in frame_item:
        return _seq_item(frame_item, seq_name, attr)
    shared = ds.get("SharedFunctionalGroupsSequence")
    if shared:
        return _seq_item(shared[0], seq_name, attr)
    return None


def _tm_seconds(value) -> float | None:
    """DICOM TM (``HHMMSS.ffffff``, parts may be cut short) as seconds since midnight."""
    t = str(value or "").strip().replace(":", "")
    if len(t) < 2 or not t.split(".")[0].isdigit():
        return None
    try:
        hh, mm, ss = int(t[0:2]), int(t[2:4] or 0), float(t[4:] or 0)
    except ValueError:
        return None
    return hh * 3600.0 + mm * 60.0 + ss


def _slices_of(ds, path: Path) -> list[_Slice]:
    """The 2D images of one dataset with their geometry (headers only), with the slice time."""
    out = _slices_of_geometry(ds, path)
    t = _tm_seconds(ds.get("AcquisitionTime")) if ds.get("AcquisitionTime") else _tm_seconds(ds.get("ContentTime"))
    for s in out:
        s.time_s = t
    return out


def _slices_of_geometry(ds, path: Path) -> list[_Slice]:
    n_frames = int(ds.get("NumberOfFrames", 1) or 1)
    instance = int(ds.get("InstanceNumber", 0) or 0)
    acq = str(ds.get("AcquisitionNumber", ""))
    rows, cols = int(ds.Rows), int(ds.Columns)
    if "PerFrameFunctionalGroupsSequence" in ds:
        per = ds.PerFrameFunctionalGroupsSequence
        if len(per) != n_frames:
            raise InputError(f"{path.name}: {len(per)} per-frame geometries for {n_frames} frames; the file is inconsistent")
        out = []
        for f, item in enumerate(per):
            ipp = _frame_attr(ds, item, "PlanePositionSequence", "ImagePositionPatient")
            iop = _frame_attr(ds, item, "PlaneOrientationSequence", "ImageOrientationPatient")
            ps = _frame_attr(ds, item, "PixelMeasuresSequence", "PixelSpacing")
            slope = _frame_attr(ds, item, "PixelValueTransformationSequence", "RescaleSlope")
            icpt = _frame_attr(ds, item, "PixelValueTransformationSequence", "RescaleIntercept")
            out.append(_Slice(
                path, f, _floats(ipp, 3, f"frame {f + 1} position", path), _floats(iop, 6, f"frame {f + 1} orientation", path),
                tuple(_floats(ps, 2, f"frame {f + 1} pixel spacing", path)), rows, cols,
                float(ds.get("RescaleSlope", 1.0) if slope is None else slope),
                float(ds.get("RescaleIntercept", 0.0) if icpt is None else icpt), instance * 100000 + f, acq,
            ))
        return out
    if n_frames != 1:
        raise InputError(f"{path.name}: {n_frames} frames without per-frame positions; their geometry is unknown")
    return [_Slice(
        path, None, _floats(ds.get("ImagePositionPatient"), 3, "ImagePositionPatient", path),
        _floats(ds.get("ImageOrientationPatient"), 6, "ImageOrientationPatient", path),
        tuple(_floats(ds.get("PixelSpacing"), 2, "PixelSpacing", path)), rows, cols,
        float(ds.get("RescaleSlope", 1.0) or 1.0), float(ds.get("RescaleIntercept", 0.0) or 0.0), instance, acq,
    )]


def _files(folder: Path) -> list[Path]:
    try:
        entries = sorted(p for p in folder.iterdir() if not p.name.startswith("."))
    except PermissionError:
        raise InputError(f"cannot read folder {folder}: permission denied") from None
    out = []
    for p in entries:
        try:
            if p.is_file():
                out.append(p)
        except PermissionError:
            raise InputError(f"cannot read {p}: permission denied") from None
    return out


def _group_headers(paths: list[Path]) -> dict[str, list]:
    """Series UID -> list of (path, header dataset), in file-name order."""
    groups: dict[str, list] = {}
    for p in paths:
        ds = _read_dataset(p, pixels=False)
        if ds is not None:
            groups.setdefault(str(ds.SeriesInstanceUID), []).append((p, ds))
    return groups


# ---------------------------------------------------------------------------- geometry
@dataclass
class _Geometry:
    """Checked geometry of a series: slices sorted along the normal, and what to do with them."""

    slices: list[_Slice]
    row: np.ndarray
    col: np.ndarray
    normal: np.ndarray
    d: np.ndarray  # slice positions along the normal, mm, ascending
    offsets: np.ndarray  # (n, 2) in-plane offset of each IPP from the first, along (row, col), mm
    spacing: np.ndarray  # (column spacing, row spacing, slice spacing) mm
    tilt_deg: float
    regular: bool
    notes: list[str]


def _check_geometry(slices: list[_Slice], what: str) -> _Geometry:
    if len(slices) < 2:
        raise InputError(f"{what} has only {len(slices)} slice; a CT volume needs several")
    iop0 = slices[0].iop
    for s in slices[1:]:
        if np.abs(s.iop - iop0).max() > IOP_ATOL:
            raise InputError(f"{what} mixes slice orientations (e.g. {s.path.name}); load one orientation per series")
        if (s.rows, s.cols) != (slices[0].rows, slices[0].cols) or np.abs(np.subtract(s.pixel_spacing, slices[0].pixel_spacing)).max() > 1e-4:
            raise InputError(f"{what} mixes image sizes or pixel spacings (e.g. {s.path.name}); its slices do not form one volume")
    row, col = iop0[:3], iop0[3:]
    if abs(np.linalg.norm(row) - 1) > 1e-3 or abs(np.linalg.norm(col) - 1) > 1e-3 or abs(row @ col) > 1e-3:
        raise InputError(f"{what} has a non-orthonormal ImageOrientationPatient; its geometry cannot be trusted")
    row, col = row / np.linalg.norm(row), col / np.linalg.norm(col)
    normal = np.cross(row, col)
    pos = np.array([s.position for s in slices])
    dd = pos @ normal
    order = np.argsort(dd, kind="stable")
    slices = [slices[i] for i in order]
    pos, dd = pos[order], dd[order]
    notes: list[str] = []

    # two acquisitions interleaved under one UID: their position ranges overlap
    acqs = sorted({s.acquisition for s in slices if s.acquisition != ""})
    if len(acqs) > 1:
        ranges = [(dd[[s.acquisition == a for s in slices]].min(), dd[[s.acquisition == a for s in slices]].max()) for a in acqs]
        ranges.sort()
        for (a0, a1), (b0, b1) in zip(ranges, ranges[1:]):
            if b0 < a1 - POS_ATOL_MM:
                raise InputError(
                    f"{what} holds {len(acqs)} acquisitions (AcquisitionNumber {', '.join(acqs[:4])}) that overlap in space; "
                    "they are not one volume: export each acquisition as its own series"
                )

    check_interleaved(slices, what)

    # duplicate positions
    keep = [0]
    for i in range(1, len(slices)):
        if dd[i] - dd[keep[-1]] < POS_ATOL_MM:
            a, b = slices[keep[-1]], slices[i]
            same_place = np.linalg.norm(a.position - b.position) < POS_ATOL_MM
            if same_place and a.pixels is None:  # headers only (list_series): content checked on load
                notes.append(f"duplicate slice position ({a.path.name}, {b.path.name})")
                continue
            if same_place and np.array_equal(a.pixels, b.pixels):
                notes.append(f"duplicate slice {b.path.name} (same position and content as {a.path.name}) ignored")
                continue
            raise InputError(
                f"{what}: two slices at the same position ({a.path.name}, {b.path.name}) with different content; "
                "the series mixes acquisitions or is damaged"
            )
        keep.append(i)
    slices = [slices[i] for i in keep]
    pos, dd = pos[keep], dd[keep]
    if len(slices) < 2:
        raise InputError(f"{what} has all its slices at one position; a CT volume needs several")

    gaps = np.diff(dd)
    g = float(np.median(gaps))
    # in-plane drift of the slice positions (gantry tilt, either encoding)
    off = np.column_stack([(pos - pos[0]) @ row, (pos - pos[0]) @ col])
    drift = np.linalg.norm(off, axis=1)
    tilt_deg = 0.0
    if drift.max() > POS_ATOL_MM:
        span = dd[-1] - dd[0]
        tilt_deg = float(np.degrees(np.arctan2(drift[-1], span)))
        # the drift must be a straight line through the slice positions (one tilt angle)
        slope = np.linalg.lstsq(np.column_stack([dd - dd[0], np.ones(len(dd))]), off, rcond=None)[0]
        resid = off - np.column_stack([dd - dd[0], np.ones(len(dd))]) @ slope
        if np.abs(resid).max() > max(0.05, 0.05 * g):
            raise InputError(f"{what}: slice positions do not lie on one line (in-plane jumps up to {np.abs(resid).max():.2f} mm); the geometry is unknown")
        notes.append(
            f"gantry tilt {tilt_deg:.1f} deg (slice positions not along the slice normal): resampled onto a regular LPS grid "
            "honouring every slice's position"
        )

    regular_spacing = bool(np.all(np.abs(gaps - g) <= SPACING_RTOL * g + POS_ATOL_MM))
    step = g
    if not regular_spacing:
        # each gap against the smallest of its neighbours (itself left out): an isolated large
        # gap in a run of regular ones means missing slices; a run of other gaps, uneven spacing
        local = np.array([min(np.r_[gaps[max(0, i - 3): i], gaps[i + 1: i + 4]], default=gaps[i]) for i in range(len(gaps))])
        ratio = gaps / np.maximum(local, 1e-6)
        worst = int(np.argmax(ratio))
        if ratio[worst] > MAX_MISSING_SLICES + 1.5:
            raise InputError(
                f"{what}: about {int(round(ratio[worst])) - 1} slices missing between {dd[worst]:.1f} and {dd[worst + 1]:.1f} mm "
                f"along the slice normal (a {gaps[worst]:.1f} mm gap in {local[worst]:.3g} mm slices); reload the complete series"
            )
        gapped = ratio > 1.5
        plain = gaps[~gapped] if (~gapped).any() else gaps
        step = float(plain.min())
        if np.any(np.abs(plain - step) > SPACING_RTOL * step + POS_ATOL_MM):
            notes.append(
                f"uneven slice spacing ({gaps.min():.3g}-{gaps.max():.3g} mm): resampled onto a regular {step:.3g} mm grid "
                "honouring every slice's position"
            )
        if gapped.any():
            n_miss = int((np.round(ratio[gapped]) - 1).sum())
            where = ", ".join(f"{dd[i]:.1f}-{dd[i + 1]:.1f} mm" for i in np.flatnonzero(gapped)[:3])
            notes.append(f"{n_miss} missing slice(s) (at {where} along the slice normal): interpolated across the gap "
                         f"on a regular {step:.3g} mm grid")
    spacing = np.array([slices[0].pixel_spacing[1], slices[0].pixel_spacing[0], step], float)
    return _Geometry(slices, row, col, normal, dd, off, spacing, tilt_deg, bool(regular_spacing and tilt_deg == 0.0), notes)


# ---------------------------------------------------------------------------- pixels
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


# ---------------------------------------------------------------------------- public
def list_series(path: str | Path) -> list[SeriesInfo]:
    """The DICOM series of a folder (or of one DICOM file), largest first.

    Args:
        path: a folder (its files; sub-folders are not searched) or one DICOM file (``~`` expanded).

    Returns:
        list of :class:`SeriesInfo`, most slices first: ``uid`` (pass it as ``series=`` to
        :func:`~monotracker.ct.volume.load_volume`), ``description``, ``modality``,
        ``slices``, ``spacing_mm`` (column, row, slice) mm, ``tilt_deg`` (gantry tilt, deg),
        ``notes`` (what loading it would say), ``ok`` False with the refusal in ``notes`` for a
        series that cannot be loaded. Empty when the folder holds no DICOM image.

    Raises:
        InputError: ``path`` does not exist or cannot be read (permission denied).
    """
    p = Path(path).expanduser()
    if not p.exists():
        raise InputError(f"no such file or folder: {p}")
    paths = _files(p) if p.is_dir() else [p]
    groups = _group_headers(paths)
    out = []
    for uid, items in groups.items():
        ds0 = items[0][1]
        desc = str(ds0.get("SeriesDescription", "") or "")
        info = SeriesInfo(uid, desc, 0, (float("nan"),) * 3, float("nan"), modality=str(ds0.get("Modality", "")),
                          files=[str(q) for q, _ in items])
        try:
            slices = [s for q, ds in items for s in _slices_of(ds, q)]
            info.slices = len(slices)
            geo = _check_geometry(slices, f"series {uid}")
            info.spacing_mm = tuple(float(x) for x in geo.spacing)
            info.tilt_deg = geo.tilt_deg
            info.notes = geo.notes
        except InputError as exc:
            info.ok = False
            info.notes = [str(exc)]
            info.slices = info.slices or len(items)
        out.append(info)
    out.sort(key=lambda s: -s.slices)
    return out


def read_dicom(path: Path, series: str | None, notes: list[str]):
    """Read a DICOM series (folder) or one DICOM file into a SimpleITK image (HU, LPS geometry),
    appending what the operator should know to ``notes``. Returns None when ``path`` holds no
    DICOM image at all (the caller gives its own hint)."""
    import SimpleITK as sitk

    paths = _files(path) if path.is_dir() else [path]
    groups = _group_headers(paths)
    if not groups:
        return None
    if series is not None:
        if series not in groups:
            raise InputError(f"series {series} is not in {path}; it holds: {', '.join(groups)}")
        uid = series
    else:
        uid = max(groups, key=lambda u: len(groups[u]))
        if len(groups) > 1:
            others = ", ".join(f"{u} ({len(v)} files)" for u, v in groups.items() if u != uid)
            notes.append(
                f"folder holds {len(groups)} DICOM series; picked the largest, {uid} ({len(groups[uid])} files); "
                f"others: {others}; choose with series=UID (CLI: --series UID, list them with --list-series)"
            )
    items = groups[uid]
    slices = [s for q, ds in items for s in _slices_of(ds, q)]
    if len(slices) < 2:
        return None if path.is_file() else _too_few(uid, len(slices))
    _load_pixels(slices)
    geo = _check_geometry(slices, f"series {uid}")
    arr, origin = _stack(geo)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing([float(x) for x in geo.spacing])
    img.SetOrigin([float(x) for x in origin])
    img.SetDirection([float(x) for x in np.column_stack([geo.row, geo.col, geo.normal]).ravel()])
    notes.append(f"DICOM series {uid}, {len(geo.slices)} slices")
    notes.extend(geo.notes)
    return img


def _too_few(uid: str, n: int):
    raise InputError(f"series {uid} has only {n} slice; a CT volume with several slices is needed")
