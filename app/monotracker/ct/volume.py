"""Loading a CT volume (DICOM series folder, NIfTI, NRRD, MHA/MHD) with SimpleITK.

Everything downstream works in physical LPS millimetres: a :class:`Volume` keeps the image's
spacing, origin and direction and converts voxel indices to LPS points and back. Indices are
SimpleITK's ``(i, j, k)`` order (i along x / columns, fastest); the NumPy ``array`` is indexed
``[k, j, i]`` (z, y, x).

Every bad input raises :class:`~monotracker.errors.InputError` with one line saying what is
wrong: missing path, empty folder, unknown series, a 2D image, a truncated or unreadable file,
intensities that are not CT Hounsfield units, absurd spacing or a non-orthonormal direction.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from monotracker.errors import InputError

log = logging.getLogger(__name__)
# ITK's own warnings go to stderr and would look like errors to the operator; we report ours.
sitk.ProcessObject.SetGlobalWarningDisplay(False)

#: File name endings SimpleITK reads for us (besides DICOM folders / single DICOM files).
VOLUME_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd", ".dcm")
#: Plausible voxel spacing for a CT, mm.
MIN_SPACING_MM = 0.05
MAX_SPACING_MM = 10.0


@dataclass
class Volume:
    """A CT volume in Hounsfield units with its physical geometry.

    ``array`` is (z, y, x) = [k, j, i], native dtype of the file (usually int16 HU).
    ``spacing_mm`` is (i, j, k); ``origin_mm`` the LPS position of voxel (0, 0, 0);
    ``direction`` the 3x3 matrix whose columns are the i, j, k axes in LPS.
    ``notes`` lists things the operator should know (e.g. which series was picked).
    """

    image: sitk.Image
    array: np.ndarray
    spacing_mm: np.ndarray
    origin_mm: np.ndarray
    direction: np.ndarray
    source: str = ""
    notes: list[str] = field(default_factory=list)

    @classmethod
    def from_image(cls, image: sitk.Image, source: str = "", notes: list[str] | None = None) -> "Volume":
        return cls(
            image=image,
            array=sitk.GetArrayFromImage(image),
            spacing_mm=np.array(image.GetSpacing(), float),
            origin_mm=np.array(image.GetOrigin(), float),
            direction=np.array(image.GetDirection(), float).reshape(3, 3),
            source=source,
            notes=list(notes or []),
        )

    @property
    def size_ijk(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.array.shape[::-1])

    @property
    def index_to_lps_matrix(self) -> np.ndarray:
        """4x4 ``T_lps_index``: homogeneous (i, j, k, 1) -> LPS mm."""
        T = np.eye(4)
        T[:3, :3] = self.direction * self.spacing_mm[None, :]
        T[:3, 3] = self.origin_mm
        return T

    def index_to_lps(self, ijk: np.ndarray) -> np.ndarray:
        """Continuous voxel indices (n, 3) in (i, j, k) order -> LPS points (n, 3), mm."""
        ijk = np.asarray(ijk, float)
        return ijk @ (self.direction * self.spacing_mm[None, :]).T + self.origin_mm

    def lps_to_index(self, lps: np.ndarray) -> np.ndarray:
        """LPS points (n, 3), mm -> continuous voxel indices (n, 3) in (i, j, k) order."""
        lps = np.asarray(lps, float)
        return ((lps - self.origin_mm) @ self.direction) / self.spacing_mm

    def zyx_to_lps(self, kji: np.ndarray) -> np.ndarray:
        """Array-order indices (n, 3) as (k, j, i) -> LPS points (n, 3), mm."""
        return self.index_to_lps(np.asarray(kji, float)[..., ::-1])

    def describe(self) -> str:
        s = self.spacing_mm
        return (
            f"{self.size_ijk[0]}x{self.size_ijk[1]}x{self.size_ijk[2]} voxels, "
            f"spacing {s[0]:.3g} x {s[1]:.3g} x {s[2]:.3g} mm"
        )


# ---------------------------------------------------------------------------- reading
def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    # ITK messages are long and multi-line; keep the part after the last "): " if any
    if "Description:" in text:
        text = text.split("Description:")[-1].strip()
    return text[:200]


def _check_nifti_complete(path: Path) -> None:
    """ITK reads a truncated NIfTI without complaint (the missing voxels come back as zeros),
    so check the data length against the NIfTI-1 header ourselves."""
    import gzip
    import struct

    opener = gzip.open if path.name.lower().endswith(".gz") else open
    try:
        with opener(path, "rb") as fh:
            hdr = fh.read(348)
            if len(hdr) < 348:
                raise InputError(f"{path.name} is truncated (incomplete NIfTI header)")
            endian = "<" if struct.unpack("<i", hdr[:4])[0] == 348 else ">"
            if struct.unpack(endian + "i", hdr[:4])[0] != 348:
                return  # NIfTI-2 or not NIfTI: leave it to ITK
            dims = struct.unpack(endian + "8h", hdr[40:56])
            bitpix = struct.unpack(endian + "h", hdr[72:74])[0]
            vox_offset = int(struct.unpack(endian + "f", hdr[108:112])[0])
            n = int(np.prod([max(1, d) for d in dims[1 : 1 + max(1, min(dims[0], 7))]], dtype=np.int64))
            need = vox_offset + n * bitpix // 8
            datatype = struct.unpack(endian + "h", hdr[70:72])[0]
            # ITK reads NaN/inf float voxels as 0 without a word: scan every float voxel here
            ftype = {16: np.dtype(endian + "f4"), 64: np.dtype(endian + "f8")}.get(datatype)
            have = 348
            skip = max(0, vox_offset - 348)
            bad = 0
            rest = b""
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
    except (EOFError, OSError, struct.error) as exc:
        raise InputError(f"{path.name} is truncated or corrupt ({_one_line(exc)})") from None
    if have < need:
        raise InputError(f"{path.name} is truncated: {have} of {need} bytes of image data")
    if bad:
        raise InputError(f"{path.name} contains {bad} NaN or infinite voxels; its values cannot be trusted")


def _read_file(path: Path) -> sitk.Image:
    if path.name.lower().endswith((".nii", ".nii.gz")):
        _check_nifti_complete(path)
    try:
        return sitk.ReadImage(str(path))
    except RuntimeError as exc:
        text = str(exc)
        if "Unable to determine ImageIO reader" in text:
            raise InputError(
                f"cannot read {path.name}: not a recognised volume (use a DICOM folder, .nii/.nii.gz, .nrrd, .mha/.mhd) or a damaged file"
            ) from None
        log.debug("ITK could not read %s: %s", path, text)
        raise InputError(f"cannot read {path.name}: the file is truncated or corrupt") from None


def _read_dicom_folder(folder: Path, series: str | None, notes: list[str]) -> sitk.Image:
    """Every slice's own geometry read and checked with pydicom (see :mod:`.dicom_series`)."""
    from monotracker.ct.dicom_series import _files, read_dicom

    entries = _files(folder)
    if not entries:
        raise InputError(f"folder {folder} is empty: point to a DICOM series folder or a volume file")
    img = read_dicom(folder, series, notes)
    if img is None:
        vols = [p.name for p in entries if p.name.lower().endswith(VOLUME_SUFFIXES[:-1])]
        hint = f" (it holds {vols[0]}: pass that file instead)" if vols else ""
        raise InputError(f"no DICOM series found in folder {folder}{hint}")
    return img


def _check_image(img: sitk.Image, name: str) -> sitk.Image:
    if img.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"{name} has {img.GetNumberOfComponentsPerPixel()} values per voxel (colour or vector image); a CT has one")
    dim = img.GetDimension()
    size = img.GetSize()
    if dim == 4 and size[3] == 1:
        img = img[:, :, :, 0]
        dim, size = 3, img.GetSize()
    if dim == 2 or (dim == 3 and min(size) < 2):
        raise InputError(f"{name} is a 2D image ({' x '.join(map(str, size))} voxels); a CT volume with several slices is needed")
    if dim != 3:
        raise InputError(f"{name} is a {dim}D image; a 3D CT volume is needed")
    sp = np.array(img.GetSpacing(), float)
    if not np.all(np.isfinite(sp)) or sp.min() < MIN_SPACING_MM or sp.max() > MAX_SPACING_MM:
        raise InputError(
            f"{name} has implausible voxel spacing {tuple(round(float(s), 4) for s in sp)} mm "
            f"(a CT has {MIN_SPACING_MM}-{MAX_SPACING_MM} mm); check the file's header"
        )
    D = np.array(img.GetDirection(), float).reshape(3, 3)
    if not np.allclose(D.T @ D, np.eye(3), atol=1e-3):
        raise InputError(f"{name} has a non-orthonormal direction matrix; its geometry cannot be trusted")
    return img


def _check_hounsfield(arr: np.ndarray, name: str) -> None:
    """Reject volumes whose values are not Hounsfield units (no air, 8-bit, unscaled 12-bit)."""
    sample = arr[:: max(1, arr.shape[0] // 32), ::4, ::4]
    if sample.size == 0:
        sample = arr
    lo, hi = np.percentile(sample, [0.5, 99.9])
    if arr.dtype == np.uint8 or (lo >= 0 and hi <= 255):
        raise InputError(f"{name} holds 0..255 values (an 8-bit picture or mask), not CT Hounsfield units")
    if lo > -500:
        raise InputError(
            f"{name} does not look like a CT in Hounsfield units: no air around the head "
            f"(lowest values ~{lo:.0f}, air is -1000 HU); is the rescale slope/intercept missing?"
        )
    if hi < 200:
        raise InputError(f"{name} does not look like a head CT: no bone or denser values (highest ~{hi:.0f} HU)")


def load_volume(path: str | Path, series: str | None = None) -> Volume:
    """Load a CT from a DICOM series folder, ``.nii``/``.nii.gz``, ``.nrrd``, ``.mha``/``.mhd``
    (or one multi-frame DICOM file).

    Args:
        path: the folder or file (``~`` expanded).
        series: Series Instance UID of the DICOM series to load (see :func:`list_series`);
            None takes the largest series of a folder and ``notes`` says so. Ignored, with a
            note, for a single file.

    Returns:
        :class:`Volume`: ``array`` (z, y, x) = [k, j, i] in HU (the file's dtype, usually
        int16), ``spacing_mm`` (i, j, k), ``origin_mm`` (LPS mm of voxel 0), ``direction``
        (3x3, columns = i, j, k axes in LPS), ``notes`` for the operator (series picked,
        resampling of irregular series, ...).

    Raises:
        InputError: one line, for every input that cannot be used: missing, empty or
            unreadable path; no image in it; an unknown ``series``; inconsistent slice
            geometry; NaN/infinite voxels; values that are not Hounsfield units.
    """
    p = Path(path).expanduser()
    try:
        return _load_volume(p, series)
    except PermissionError as exc:
        raise InputError(f"cannot read {exc.filename or p}: permission denied") from None


def _load_volume(p: Path, series: str | None) -> Volume:
    notes: list[str] = []
    if not p.exists():
        raise InputError(f"no such file or folder: {p}")
    if p.is_dir():
        img = _read_dicom_folder(p, series, notes)
    else:
        if p.stat().st_size == 0:
            raise InputError(f"{p.name} is empty (0 bytes)")
        img = None
        if not p.name.lower().endswith(VOLUME_SUFFIXES[:-1]):
            from monotracker.ct.dicom_series import read_dicom

            img = read_dicom(p, series, notes)  # multi-frame (enhanced) CT; None for other files
        if img is None:
            img = _read_file(p)
        if series is not None and not notes:
            notes.append("series= ignored: the input is a single file")
    name = p.name or str(p)
    img = _check_image(img, name)
    vol = Volume.from_image(img, source=str(p), notes=notes)
    if vol.array.dtype.kind == "f":
        bad = int(np.count_nonzero(~np.isfinite(vol.array)))  # every voxel, not a sample
        if bad:
            raise InputError(f"{name} contains {bad} NaN or infinite voxels; its values cannot be trusted")
    _check_hounsfield(vol.array, name)
    log.info("loaded %s: %s", p, vol.describe())
    return vol
