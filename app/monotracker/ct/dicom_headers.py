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


def _number(value, default: float, what: str, path: Path) -> float:
    """One finite number from a header value (DS/IS, possibly a string), ``default`` when absent."""
    if value is None or (isinstance(value, str) and not value.strip()):
        return default
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = float("nan")
    if not np.isfinite(x):
        raise InputError(f"{path.name}: {what} is malformed ({str(value)[:40]!r}); its values cannot be trusted")
    return x


def _rescale(slope, intercept, path: Path, where: str = "") -> tuple[float, float]:
    """(slope, intercept) of HU = slope * stored + intercept; a zero slope is refused (it would
    make every voxel the same value)."""
    m = _number(slope, 1.0, f"{where}RescaleSlope", path)
    b = _number(intercept, 0.0, f"{where}RescaleIntercept", path)
    if m == 0.0:
        raise InputError(f"{path.name}: {where}RescaleSlope is 0; its values cannot be trusted")
    return m, b


def _looks_like_dicom(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            head = fh.read(132)
    except OSError:
        return False
    return head[128:132] == b"DICM" or path.suffix.lower() in (".dcm", ".dicom", ".ima") or _headless(head)


def _headless(head: bytes) -> bool:
    """A DICOM data set written without the 128-byte preamble and "DICM" (older scanners and
    PACS exports, ACR-NEMA style; files often without an extension): it starts with a group
    0008 (or 0002) tag, little endian, element below 0x0100."""
    return len(head) >= 8 and head[0:2] in (b"\x08\x00", b"\x02\x00") and head[3:4] == b"\x00"


def _read_headless(path: Path, pixels: bool):
    """The data set of a file without preamble when it starts like one, else None."""
    pydicom = _pydicom()
    try:
        with open(path, "rb") as fh:
            if not _headless(fh.read(8)):
                return None
        ds = pydicom.dcmread(str(path), stop_before_pixels=not pixels, force=True)
    except PermissionError:
        raise InputError(f"cannot read {path}: permission denied") from None
    except Exception as exc:  # noqa: BLE001 - pydicom raises many kinds on a damaged file
        raise InputError(f"{path.name} is a truncated or corrupt DICOM file ({type(exc).__name__})") from None
    _name_transfer_syntax(ds)
    return ds


def _name_transfer_syntax(ds) -> None:
    """A file without meta header names no transfer syntax, and pydicom will not decode pixels
    without one: name the (uncompressed) encoding pydicom found the data set in."""
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRBigEndian, ExplicitVRLittleEndian, ImplicitVRLittleEndian

    if "TransferSyntaxUID" in getattr(ds, "file_meta", {}):
        return
    implicit, little = ds.original_encoding
    if not hasattr(ds, "file_meta"):
        ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = (ImplicitVRLittleEndian if implicit else
                                      ExplicitVRLittleEndian if little else ExplicitVRBigEndian)


def _read_dataset(path: Path, pixels: bool):
    """pydicom dataset, None for a file that is not a DICOM image; InputError for a damaged one."""
    pydicom = _pydicom()
    try:
        ds = pydicom.dcmread(str(path), stop_before_pixels=not pixels)
    except PermissionError:
        raise InputError(f"cannot read {path}: permission denied") from None
    except pydicom.errors.InvalidDicomError:
        ds = _read_headless(path, pixels)
        if ds is None:
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
    n_frames = int(_number(ds.get("NumberOfFrames"), 1, "NumberOfFrames", path) or 1)
    instance = int(_number(ds.get("InstanceNumber"), 0, "InstanceNumber", path))
    acq = str(ds.get("AcquisitionNumber", ""))
    rows = int(_number(ds.get("Rows"), 0, "Rows", path))
    cols = int(_number(ds.get("Columns"), 0, "Columns", path))
    if rows < 1 or cols < 1 or n_frames < 1:
        raise InputError(f"{path.name}: Rows, Columns or NumberOfFrames missing or not positive; the image size is unknown")
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
            m, b = _rescale(ds.get("RescaleSlope") if slope is None else slope,
                            ds.get("RescaleIntercept") if icpt is None else icpt, path, f"frame {f + 1} ")
            out.append(_Slice(
                path, f, _floats(ipp, 3, f"frame {f + 1} position", path), _floats(iop, 6, f"frame {f + 1} orientation", path),
                tuple(_floats(ps, 2, f"frame {f + 1} pixel spacing", path)), rows, cols,
                m, b, instance * 100000 + f, acq,
            ))
        return out
    if n_frames != 1:
        raise InputError(f"{path.name}: {n_frames} frames without per-frame positions; their geometry is unknown")
    m, b = _rescale(ds.get("RescaleSlope"), ds.get("RescaleIntercept"), path)
    return [_Slice(
        path, None, _floats(ds.get("ImagePositionPatient"), 3, "ImagePositionPatient", path),
        _floats(ds.get("ImageOrientationPatient"), 6, "ImageOrientationPatient", path),
        tuple(_floats(ds.get("PixelSpacing"), 2, "PixelSpacing", path)), rows, cols,
        m, b, instance, acq,
    )]


#: Most files searched under a folder that holds a DICOMDIR (a CD/DVD or PACS export).
MAX_DICOMDIR_FILES = 100_000


def _files(folder: Path) -> list[Path]:
    """The files of ``folder`` (not its sub-folders), by name; for a folder that holds a DICOMDIR
    (a CD/DVD or USB export: the images sit in sub-folders such as ``DICOM/ST000/SE000/IM000``)
    every file under it, the DICOMDIR itself left out."""
    out = _plain_files(folder)
    if any(p.name.upper() == "DICOMDIR" for p in out):
        out = []
        try:
            for p in sorted(folder.rglob("*")):
                if p.name.startswith(".") or p.name.upper() == "DICOMDIR" or not p.is_file():
                    continue
                out.append(p)
                if len(out) > MAX_DICOMDIR_FILES:
                    raise InputError(f"{folder} holds more than {MAX_DICOMDIR_FILES} files under its DICOMDIR; "
                                     "point to the folder of one series")
        except PermissionError as exc:
            raise InputError(f"cannot read {exc.filename or folder}: permission denied") from None
    return out


def _plain_files(folder: Path) -> list[Path]:
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


#: SOP classes never part of a CT volume even when filed under its series: secondary captures
#: (screen saves, dose screens; single- and multi-frame variants 1.2.840.10008.5.1.4.1.1.7.x).
NON_VOLUME_SOP_PREFIX = "1.2.840.10008.5.1.4.1.1.7"


def _image_type(ds) -> list[str]:
    v = ds.get("ImageType")
    if v is None:
        return []
    return [str(x).strip().upper() for x in ([v] if isinstance(v, str) else v)]


def _non_volume_kind(ds) -> str | None:
    """Why an image of a series is not one of its volume's slices, or None: a localizer / scout
    (ImageType LOCALIZER), a secondary capture (a screen save or dose screen)."""
    if "LOCALIZER" in _image_type(ds):
        return "localizer"
    sop = str(ds.get("SOPClassUID", "") or getattr(getattr(ds, "file_meta", None), "MediaStorageSOPClassUID", "") or "")
    if sop == NON_VOLUME_SOP_PREFIX or sop.startswith(NON_VOLUME_SOP_PREFIX + "."):  # not the VL classes ...1.1.77.x
        return "secondary capture"
    return None


def split_volume_images(items: list) -> tuple[list, list[str]]:
    """The (path, header) items of one series that are slices of its volume, and a note naming
    what was left out (localizers / scouts and secondary captures filed under the same series:
    they have other orientations, sizes or no position at all and are not part of the volume)."""
    kept, left = [], {}
    for q, ds in items:
        kind = _non_volume_kind(ds)
        if kind is None:
            kept.append((q, ds))
        else:
            left.setdefault(kind, []).append(q.name)
    notes = [f"{len(names)} {kind} image(s) in the series left out ({', '.join(names[:3])}{', ...' if len(names) > 3 else ''}): "
             "not slices of the volume" for kind, names in left.items()]
    return kept, notes


def modality_refusal(items: list, what: str) -> str | None:
    """One line when the series is not a CT (MR, PET, ...): the fiducial detection thresholds
    Hounsfield units, which only a CT has; None for CT (or no Modality written)."""
    mods = sorted({str(ds.get("Modality", "") or "").strip().upper() for _, ds in items} - {""})
    other = [m for m in mods if m != "CT"]
    if other:
        return (f"{what} is {'/'.join(other)} (Modality), not CT: the fiducial detection needs Hounsfield units "
                "from a CT scan of the head with its fiducials")
    return None
