"""The NIfTI-1 header read by ourselves, for what ITK reads silently wrong or reports in words
that send the operator after the wrong problem (:func:`monotracker.ct.volume.load_volume`):

* **truncated data** (ITK reads the missing voxels as zeros) and **NaN / infinite float
  voxels** (ITK reads them as 0): refused;
* **no orientation** (``qform_code = sform_code = 0``): ITK places voxel 0 at (0, 0, 0) mm with
  the grid along L, P, S. Spacing and the voxel grid are intact, so distances, the fiducials'
  constellation and a plan made on this CT are right in the CT's own frame, but the image may
  be mirrored and turned: left/right and the L/R/A/P/S/I letters on the slices may be wrong.
  Loaded with a ``WARNING`` note (kept with the CT, shown by the CLI and the app's CT step)
  rather than refused: the registration works in the CT's own frame and a mirrored CT is not a
  rigid copy of the head, so its fiducials do not register (the FRE gate refuses) unless their
  layout is itself mirror-symmetric, which the warning names;
* **a sheared sform** (an affine registration's output): ITK refuses with "no orthonormal
  definition found" (which reads as a corrupt file) when there is no qform, and silently uses
  the qform when there is one. Refused with the shear angle and what to do / noted;
* **the scale** (``scl_slope``, ``scl_inter``) that turned the stored values into the ones
  loaded, named when they are not Hounsfield units.

NIfTI-2 files (540-byte header) are left to ITK.
"""

from __future__ import annotations

import gzip
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monotracker.errors import InputError

#: Largest departure from 90 deg between two sform axes still read as a rigid grid, deg.
SHEAR_TOL_DEG = 0.1


@dataclass(frozen=True)
class NiftiHeader:
    """The fields of a NIfTI-1 header that loading checks (units as in the file: pixdim in
    ``xyzt_units``, normally mm; ``srow`` the sform's 3x4 rows, RAS mm)."""

    endian: str
    dims: tuple
    datatype: int
    bitpix: int
    pixdim: tuple
    vox_offset: int
    scl_slope: float
    scl_inter: float
    xyzt_units: int
    qform_code: int
    sform_code: int
    srow: np.ndarray

    @property
    def n_voxels(self) -> int:
        return int(np.prod([max(1, d) for d in self.dims], dtype=np.int64))

    @property
    def data_bytes(self) -> int:
        return self.n_voxels * self.bitpix // 8

    @property
    def scaled(self) -> bool:
        """True when the stored values are rescaled on reading (slope not 0 or 1, or an offset)."""
        return self.scl_slope not in (0.0, 1.0) or (self.scl_slope != 0.0 and self.scl_inter != 0.0)

    def scale_text(self) -> str:
        return f"scl_slope {self.scl_slope:.6g} and scl_inter {self.scl_inter:.6g}"


def _opener(path: Path):
    return gzip.open if path.name.lower().endswith(".gz") else open


def read_header(path: Path) -> NiftiHeader | None:
    """The NIfTI-1 header of ``path`` (``.nii``/``.nii.gz``), None for NIfTI-2 or a file that is
    not NIfTI (left to ITK). InputError for a truncated header; PermissionError passes."""
    try:
        with _opener(path)(path, "rb") as fh:
            hdr = fh.read(348)
    except PermissionError:
        raise
    except (EOFError, OSError) as exc:
        raise InputError(f"{path.name} is truncated or corrupt ({' '.join(str(exc).split())[:120]})") from None
    if len(hdr) < 348:
        raise InputError(f"{path.name} is truncated (incomplete NIfTI header)")
    endian = "<" if struct.unpack("<i", hdr[:4])[0] == 348 else ">"
    if struct.unpack(endian + "i", hdr[:4])[0] != 348:
        return None

    def f(fmt: str, off: int):
        return struct.unpack_from(endian + fmt, hdr, off)

    dim = f("8h", 40)
    n = max(1, min(int(dim[0]), 7))
    return NiftiHeader(
        endian=endian, dims=tuple(int(d) for d in dim[1:1 + n]), datatype=int(f("h", 70)[0]), bitpix=int(f("h", 72)[0]),
        pixdim=tuple(float(x) for x in f("8f", 76)), vox_offset=int(f("f", 108)[0]), scl_slope=float(f("f", 112)[0]),
        scl_inter=float(f("f", 116)[0]), xyzt_units=int(hdr[123]), qform_code=int(f("h", 252)[0]),
        sform_code=int(f("h", 254)[0]), srow=np.array([f("4f", 280), f("4f", 296), f("4f", 312)], float))


def check_data(path: Path, hdr: NiftiHeader) -> None:
    """Refuse a truncated data block (ITK reads the missing voxels as zeros without a word) or
    NaN / infinite float voxels (ITK reads them as 0): every float voxel is scanned. An
    uncompressed integer file is checked by its size alone (nothing in it can be NaN)."""
    need = hdr.vox_offset + hdr.data_bytes
    ftype = {16: np.dtype(hdr.endian + "f4"), 64: np.dtype(hdr.endian + "f8")}.get(hdr.datatype)
    gz = path.name.lower().endswith(".gz")
    if ftype is None and not gz:
        have = path.stat().st_size
        if have < need:
            raise InputError(f"{path.name} is truncated: {have} of {need} bytes of image data")
        return
    have, bad, rest = 348, 0, b""
    skip = max(0, hdr.vox_offset - 348)
    try:
        with _opener(path)(path, "rb") as fh:
            fh.read(348)
            while True:
                chunk = fh.read(1 << 22)
                if not chunk:
                    break
                have += len(chunk)
                if ftype is None:
                    continue
                if skip:
                    cut = min(skip, len(chunk))
                    chunk, skip = chunk[cut:], skip - cut
                buf = rest + chunk
                usable = len(buf) - len(buf) % ftype.itemsize
                bad += int(np.count_nonzero(~np.isfinite(np.frombuffer(buf[:usable], ftype))))
                rest = buf[usable:]
    except PermissionError:
        raise
    except (EOFError, OSError, struct.error) as exc:
        raise InputError(f"{path.name} is truncated or corrupt ({' '.join(str(exc).split())[:120]})") from None
    if have < need:
        raise InputError(f"{path.name} is truncated: {have} of {need} bytes of image data")
    if bad:
        raise InputError(f"{path.name} contains {bad} NaN or infinite voxels; its values cannot be trusted")


def _axis_angles_deg(A: np.ndarray) -> np.ndarray:
    """Angles between the three columns of ``A`` (i-j, i-k, j-k), deg."""
    u = A / np.maximum(np.linalg.norm(A, axis=0), 1e-12)
    return np.degrees(np.arccos(np.clip([u[:, 0] @ u[:, 1], u[:, 0] @ u[:, 2], u[:, 1] @ u[:, 2]], -1.0, 1.0)))


def orientation_notes(hdr: NiftiHeader, name: str) -> list[str]:
    """What the header's orientation means for loading (module docstring): a ``WARNING`` note
    for no orientation, a note when a sheared sform is passed over for the qform; InputError for
    a sheared sform with no qform to fall back on."""
    if hdr.qform_code <= 0 and hdr.sform_code <= 0:
        return [f"WARNING: {name} has no orientation (NIfTI qform_code and sform_code are 0): it was loaded as if its "
                "voxel axes ran along L, P, S from (0, 0, 0) mm. Distances and the fiducials are right in the CT's own "
                "frame, but the image may be mirrored or turned: left/right and the L/R/A/P/S/I letters on the slices may "
                "be wrong, and a mirror-symmetric fiducial layout would register mirrored. Check left/right on a known "
                "marker, or export the CT again with its orientation (DICOM, or NIfTI with a qform)"]
    if hdr.sform_code > 0:
        A = hdr.srow[:, :3]
        ang = _axis_angles_deg(A)
        worst = float(np.max(np.abs(ang - 90.0)))
        if np.all(np.isfinite(A)) and np.linalg.matrix_rank(A) == 3 and worst > SHEAR_TOL_DEG:
            pair = ("i-j", "i-k", "j-k")[int(np.argmax(np.abs(ang - 90.0)))]
            what = f"its sform (orientation) is sheared: the {pair} voxel axes are {ang[int(np.argmax(np.abs(ang - 90.0)))]:.1f} deg apart, not 90"
            if hdr.qform_code <= 0:
                raise InputError(f"{name}: {what}, and it has no qform to fall back on. A CT's grid is not sheared (the "
                                 "sform of an affine registration's output?): resample it onto a regular grid first (e.g. "
                                 "3D Slicer's Resample Scalar Volume, or harden the transform), or load the original CT")
            return [f"{name}: {what}; its qform (the scanner's rigid orientation) was used instead"]
    return []


def scale_hint(hdr: NiftiHeader | None) -> str:
    """Words naming the header's rescale for a refusal of the values loaded ('' when none)."""
    if hdr is None or not hdr.scaled:
        return ""
    return (f"; its header scales the stored values by {hdr.scale_text()} (a CT's are 1 and 0, or 1 and -1024): "
            "correct scl_slope / scl_inter or export the CT again")
