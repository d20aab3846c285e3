"""DICOM headers read with pydicom: the files of a folder, grouped by series, and each 2D image
(a single-frame file or one frame of an enhanced multi-frame file) with its own geometry
(ImagePositionPatient, ImageOrientationPatient, PixelSpacing; LPS mm) and rescale
(:mod:`monotracker.ct.dicom_series`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monotracker.errors import InputError


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
