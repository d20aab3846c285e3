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
Localizers (scouts) and secondary captures filed under the series are left out with a note; a
series that is not CT (Modality MR, PT, ...) is refused. Without ``series=`` a folder with
several series gives, with a note, the finest original (not derived) series among those covering
the patient (>= 90 % of the widest), when they all belong to one scan (one FrameOfReferenceUID);
series of different scans, or without a frame of reference, are refused: choose one.
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
from monotracker.ct.dicom_headers import (  # _files used by volume.py
    _files,
    _group_headers,
    _image_type,
    _slices_of,
    modality_refusal,
    split_volume_images,
)
from monotracker.ct.coverage import Coverage, MissingSlab
from monotracker.ct.dicom_pixels import _load_pixels, _stack
from monotracker.ct.memory import check_fits
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
    #: FrameOfReferenceUID: series with the same one are one scan (a series without one is a
    #: scan of its own: nothing says it shares the others' coordinates).
    frame_of_reference: str = field(default="", repr=False)
    #: Volume the series covers (pixel grid x first to last slice position), mm^3 (NaN when it
    #: cannot be loaded), and its voxel count.
    extent_mm3: float = field(default=float("nan"), repr=False)
    #: ImageType DERIVED (a reformat, MIP or thick slab made from the original slices).
    derived: bool = field(default=False, repr=False)
    voxels: int = field(default=0, repr=False)
    #: Slice grid (orientation, positions, pixel grid), rounded: equal for two reconstructions
    #: of one acquisition (e.g. a soft-tissue and a bone kernel).
    grid_key: tuple = field(default=(), repr=False)

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
        path: a folder (its files; sub-folders are not searched, except under a DICOMDIR) or
            one DICOM file (``~`` expanded).

    Returns:
        list of :class:`SeriesInfo`, most slices first: ``uid`` (pass it as ``series=`` to
        :func:`~monotracker.ct.volume.load_volume`), ``description``, ``modality``,
        ``slices``, ``spacing_mm`` (column, row, slice) mm, ``tilt_deg`` (gantry tilt, deg),
        ``notes`` (what loading it would say), ``ok`` False with the refusal in ``notes`` for a
        series that cannot be loaded (not CT, only localizers, bad geometry). Empty when the
        folder holds no DICOM image.

    Raises:
        InputError: ``path`` does not exist or cannot be read (permission denied).
    """
    p = Path(path).expanduser()
    if not p.exists():
        raise InputError(f"no such file or folder: {p}")
    if p.is_file() and p.name.upper() == "DICOMDIR":
        p = p.parent
    paths = _files(p) if p.is_dir() else [p]
    out = [_series_info(uid, items) for uid, items in _group_headers(paths).items()]
    out.sort(key=lambda s: -s.slices)
    return out


def _series_info(uid: str, items: list) -> SeriesInfo:
    """What loading series ``uid`` (its (path, header) items) would give, from the headers."""
    ds0 = items[0][1]
    info = SeriesInfo(uid, str(ds0.get("SeriesDescription", "") or ""), 0, (float("nan"),) * 3, float("nan"),
                      modality=str(ds0.get("Modality", "")), files=[str(q) for q, _ in items],
                      # no frame of reference: nothing says it is the same scan as another series
                      frame_of_reference=str(ds0.get("FrameOfReferenceUID", "") or "") or f"(none: series {uid})")
    kept, left = split_volume_images(items)
    try:
        why = modality_refusal(kept, f"series {uid}")  # the CT's slices; a screen save may say OT
        if why:
            raise InputError(why)
        if not kept:
            raise InputError(f"series {uid} holds only localizer / secondary-capture images; not a CT volume")
        slices = [s for q, ds in kept for s in _slices_of(ds, q)]
        info.slices = len(slices)
        geo = _check_geometry(slices, f"series {uid}")
        info.spacing_mm = tuple(float(x) for x in geo.spacing)
        info.tilt_deg = geo.tilt_deg
        info.notes = left + geo.notes
        s0 = geo.slices[0]
        sx, sy, sz = geo.spacing
        info.voxels = s0.rows * s0.cols * len(geo.slices)
        info.extent_mm3 = float(s0.cols * sx * s0.rows * sy * (geo.d[-1] - geo.d[0]))
        info.derived = any(_image_type(ds)[:1] == ["DERIVED"] for _, ds in kept)
        info.grid_key = (s0.rows, s0.cols, tuple(np.round(s0.pixel_spacing, 3)), tuple(np.round(s0.iop, 3)),
                         tuple(map(tuple, np.round([s.position for s in geo.slices], 1))))
    except InputError as exc:
        info.ok = False
        info.notes = [str(exc)]
        info.slices = info.slices or len(kept)
    return info


def _pick_series(path: Path, groups: dict, notes: list[str]) -> str:
    """The series to load when none was named: among the loadable CT series that cover the
    patient (>= 90 % of the widest extent), the original one (not a DERIVED reformat, MIP or
    slab) with the finest slices, then the finest pixels, with a note, when they all belong to
    one scan (one frame of reference: they give the same fiducial positions); refused when they
    come from different scans or have no frame of reference (which one has the fiducials is the
    operator's call), or when none can be loaded."""
    infos = [_series_info(uid, items) for uid, items in groups.items()]
    good = [i for i in infos if i.ok]
    hint = "choose with series=UID (CLI: --series UID, list them with --list-series)"
    if not good:
        big = max(infos, key=lambda i: i.slices)
        raise InputError(f"none of the {len(infos)} DICOM series in {path} is a loadable CT volume; "
                         f"the largest, {big.uid}: {big.notes[0] if big.notes else 'no slices'}")
    scans = sorted({i.frame_of_reference for i in good})
    if len(scans) > 1:
        listed = "; ".join(f"{i.uid} ({i.description or 'no description'}, {i.slices} slices)" for i in good[:4])
        raise InputError(f"{path} holds CT series of {len(scans)} different scans (frames of reference): {listed}; "
                         f"which one has the fiducials cannot be guessed: {hint}")
    # the original (not derived: no reformat, MIP or thick slab) series among those that cover
    # the patient (>= 90 % of the largest extent), the finest slices first, then the finest pixels
    widest = max(i.extent_mm3 for i in good)
    covering = [i for i in good if i.extent_mm3 >= 0.9 * widest]
    pick = min(covering, key=lambda i: (i.derived, round(i.spacing_mm[2], 3), round(i.spacing_mm[0] * i.spacing_mm[1], 4),
                                        -i.extent_mm3, i.uid))
    same = [i.uid for i in good if i is not pick and i.grid_key == pick.grid_key]
    others = [f"{i.uid} ({i.description or 'no description'}, {i.slices} slices{'' if i.ok else ', cannot be loaded'})"
              for i in infos if i is not pick and i.uid not in same]
    sp = " x ".join(f"{x:.3g}" for x in pick.spacing_mm)
    text = (f"folder holds {len(infos)} DICOM series of one scan; picked {pick.uid} ({pick.description or 'no description'}, "
            f"{pick.slices} slices, {sp} mm: the finest original series covering the patient)")
    if same:
        text += (f"; {', '.join(same)} has the same slice grid (another reconstruction of the same scan, e.g. "
                 "another kernel): the same fiducial positions")
    if others:
        text += f"; others: {', '.join(others)}"
    notes.append(f"{text}; {hint}")
    return pick.uid


def read_dicom(path: Path, series: str | None, notes: list[str], coverage: Coverage | None = None):
    """Read a DICOM series (folder) or one DICOM file into a SimpleITK image (HU, LPS geometry),
    appending what the operator should know to ``notes`` and, into ``coverage``, where the
    grid holds no acquired data (resampling's padding value, slabs of missing slices). Returns
    None when ``path`` holds no DICOM image at all (the caller gives its own hint)."""
    import SimpleITK as sitk

    if path.is_file() and path.name.upper() == "DICOMDIR":
        path = path.parent
    paths = _files(path) if path.is_dir() else [path]
    groups = _group_headers(paths)
    if not groups:
        return None
    if series is not None:
        if series not in groups:
            raise InputError(f"series {series} is not in {path}; it holds: {', '.join(groups)}")
        uid = series
    elif len(groups) > 1:
        uid = _pick_series(path, groups, notes)
    else:
        uid = next(iter(groups))
    items, left = split_volume_images(groups[uid])
    why = modality_refusal(items, f"series {uid}")  # the CT's slices; a screen save may say OT
    if why:
        raise InputError(why)
    notes.extend(left)
    slices = [s for q, ds in items for s in _slices_of(ds, q)]
    if len(slices) < 2:
        return None if path.is_file() else _too_few(uid, len(slices))
    s0 = slices[0]
    # pixels read as int32 per slice, stacked, then int16, the ITK image and its NumPy copy
    check_fits(f"series {uid}", (s0.cols, s0.rows, len(slices)), "int16", 2, copies=7.0)
    _load_pixels(slices)
    geo = _check_geometry(slices, f"series {uid}")
    st = _stack(geo)
    img = sitk.GetImageFromArray(st.array)
    img.SetSpacing([float(x) for x in st.spacing])
    img.SetOrigin([float(x) for x in st.origin])
    img.SetDirection([float(x) for x in st.direction.ravel()])
    notes.append(f"DICOM series {uid}, {len(geo.slices)} slices")
    notes.extend(geo.notes)
    notes.extend(st.notes)
    if coverage is not None:
        coverage.pad_hu = st.pad_hu
        coverage.lattice = st.lattice
        coverage.missing = [MissingSlab(geo.normal.copy(), lo, hi, k) for lo, hi, k in geo.missing]
    return img


def _too_few(uid: str, n: int):
    raise InputError(f"series {uid} has only {n} slice; a CT volume with several slices is needed")
