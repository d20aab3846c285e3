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

from monotracker.ct.dicom_geometry import (  # noqa: F401 - public constants kept at this path
    IOP_ATOL,
    MAX_MISSING_SLICES,
    POS_ATOL_MM,
    SPACING_RTOL,
    _check_geometry,
)
from monotracker.ct.dicom_headers import _files, _group_headers, _slices_of  # noqa: F401 - _files used by volume.py
from monotracker.ct.dicom_pixels import _load_pixels, _stack
from monotracker.errors import InputError

log = logging.getLogger(__name__)


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
