"""Loading a CT volume (DICOM series folder, NIfTI, NRRD, MHA/MHD) with SimpleITK.

Everything downstream works in physical LPS millimetres: a :class:`Volume` keeps the image's
spacing, origin and direction and converts voxel indices to LPS points and back. Indices are
SimpleITK's ``(i, j, k)`` order (i along x / columns, fastest); the NumPy ``array`` is indexed
``[k, j, i]`` (z, y, x).

Every bad input raises :class:`~monotracker.errors.InputError` with one line saying what is
wrong and what to do: missing path, empty folder, unknown series, a 2D image, a truncated file, a
file or folder this user may not read (owner, mode, the user we run as), a volume larger than the
memory left (checked before reading), intensities that are not CT Hounsfield units (the file's
rescale named), spacing written in cm, absurd spacing or sheared axes. A NIfTI without
orientation loads with a ``WARNING`` note (:mod:`.nifti_header` says why it is not refused).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from monotracker.ct.coverage import Coverage
from monotracker.ct.file_access import check_readable, permission_error
from monotracker.ct.memory import check_fits, is_allocation_failure, too_big
from monotracker.ct.nifti_header import NiftiHeader, check_data, orientation_notes, read_header, scale_hint
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
    ``notes`` lists things the operator should know (e.g. which series was picked); a note
    starting with ``WARNING`` is one the operator must act on (e.g. no orientation in the file).
    ``coverage`` says where the grid holds no acquired data (:mod:`.coverage`).
    """

    image: sitk.Image
    array: np.ndarray
    spacing_mm: np.ndarray
    origin_mm: np.ndarray
    direction: np.ndarray
    source: str = ""
    notes: list[str] = field(default_factory=list)
    #: Where the grid holds no acquired data (padding value, missing slices): see :mod:`.coverage`.
    coverage: Coverage = field(default_factory=Coverage)

    @classmethod
    def from_image(cls, image: sitk.Image, source: str = "", notes: list[str] | None = None,
                   coverage: Coverage | None = None) -> "Volume":
        return cls(
            image=image,
            array=sitk.GetArrayFromImage(image),
            spacing_mm=np.array(image.GetSpacing(), float),
            origin_mm=np.array(image.GetOrigin(), float),
            direction=np.array(image.GetDirection(), float).reshape(3, 3),
            source=source,
            notes=list(notes or []),
            coverage=coverage or Coverage(),
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
        """LPS points (n, 3), mm -> continuous voxel indices (n, 3) in (i, j, k) order; the
        inverse of :meth:`index_to_lps` for any direction matrix (a sheared grid too: its
        transpose is the inverse only for orthonormal directions)."""
        lps = np.asarray(lps, float)
        return np.linalg.solve(self.direction * self.spacing_mm[None, :], (lps - self.origin_mm).T).T

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
def _pixel_bytes(pixel_id: int) -> tuple[int, str]:
    """(bytes per voxel, NumPy type name) of an ITK pixel type."""
    a = sitk.GetArrayViewFromImage(sitk.Image([1, 1, 1], pixel_id))
    return a.dtype.itemsize, a.dtype.name


def _check_memory(path: Path) -> None:
    """Refuse, before ITK reads a voxel, a volume that does not fit in the memory this process
    may still use (:mod:`.memory`): the ITK image and its NumPy copy are both held."""
    r = sitk.ImageFileReader()
    r.SetFileName(str(path))
    try:
        r.ReadImageInformation()
    except RuntimeError:
        return  # ITK's own read says what is wrong
    nbytes, dtype = _pixel_bytes(r.GetPixelID())
    nbytes *= max(1, r.GetNumberOfComponents())
    check_fits(path.name, r.GetSize(), dtype, nbytes, copies=2.0)


def _read_file(path: Path, notes: list[str]) -> tuple[sitk.Image, NiftiHeader | None]:
    """The image of a volume file, and its NIfTI header (None for other formats): the NIfTI
    checks of :mod:`.nifti_header` first (their notes appended to ``notes``), then the memory
    check, then ITK."""
    hdr = None
    if path.name.lower().endswith((".nii", ".nii.gz")):
        hdr = read_header(path)
        if hdr is not None:
            check_data(path, hdr)
            notes.extend(orientation_notes(hdr, path.name))
    _check_memory(path)
    try:
        return sitk.ReadImage(str(path)), hdr
    except RuntimeError as exc:
        text = str(exc)
        if is_allocation_failure(exc):
            raise _memory_refusal(path) from None
        if "Unable to determine ImageIO reader" in text:
            raise InputError(
                f"cannot read {path.name}: not a recognised volume (use a DICOM folder, .nii/.nii.gz, .nrrd, .mha/.mhd) or a damaged file"
            ) from None
        if "orthonormal" in text:
            raise InputError(f"{path.name}: its orientation is not a rotation (sheared or degenerate axes); a CT's grid has "
                             "perpendicular axes: resample it onto a regular grid first, or load the original CT") from None
        log.debug("ITK could not read %s: %s", path, text)
        raise InputError(f"cannot read {path.name}: the file is truncated or corrupt") from None


def _memory_refusal(path: Path) -> InputError:
    r = sitk.ImageFileReader()
    r.SetFileName(str(path))
    try:
        r.ReadImageInformation()
        nbytes, dtype = _pixel_bytes(r.GetPixelID())
        size = r.GetSize()
    except RuntimeError:
        return InputError(f"{path.name} is too large for this machine's memory: crop or resample it, or use a machine with more memory")
    n = float(np.prod(size, dtype=np.float64))
    return too_big(path.name, size, dtype, nbytes, 2.0 * n * nbytes)


def _read_dicom_folder(folder: Path, series: str | None, notes: list[str], coverage: Coverage) -> sitk.Image:
    """Every slice's own geometry read and checked with pydicom (see :mod:`.dicom_series`)."""
    from monotracker.ct.dicom_series import _files, read_dicom

    entries = _files(folder)
    if not entries:
        raise InputError(f"folder {folder} is empty: point to a DICOM series folder or a volume file")
    img = read_dicom(folder, series, notes, coverage)
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
    _check_spacing_units(sp, np.array(img.GetSize()), name)
    if not np.all(np.isfinite(sp)) or sp.min() < MIN_SPACING_MM or sp.max() > MAX_SPACING_MM:
        raise InputError(
            f"{name} has implausible voxel spacing {tuple(round(float(s), 4) for s in sp)} mm "
            f"(a CT has {MIN_SPACING_MM}-{MAX_SPACING_MM} mm); check the file's header"
        )
    D = np.array(img.GetDirection(), float).reshape(3, 3)
    if not np.allclose(D.T @ D, np.eye(3), atol=1e-3):
        u = D / np.maximum(np.linalg.norm(D, axis=0), 1e-12)
        ang = np.degrees(np.arccos(np.clip([u[:, 0] @ u[:, 1], u[:, 0] @ u[:, 2], u[:, 1] @ u[:, 2]], -1, 1)))
        raise InputError(f"{name}: its voxel axes are not perpendicular (sheared: {ang[0]:.1f}, {ang[1]:.1f}, {ang[2]:.1f} deg "
                         "apart, not 90); a CT's grid is not sheared (an affine registration's output?): resample it onto a "
                         "regular grid first, or load the original CT")
    return img


#: A head CT is at least this wide across its slices, mm (a scan of only the fiducial patch is
#: ~80 mm); smaller with sub-:data:`CM_SUSPECT_SPACING_MM` voxels reads as spacing in cm.
MIN_HEAD_FOV_MM = 60.0
CM_SUSPECT_SPACING_MM = 0.25


def _check_spacing_units(sp: np.ndarray, size: np.ndarray, name: str) -> None:
    """Refuse spacing that was written in cm (DICOM PixelSpacing and NIfTI pixdim are mm): the
    scan would then be a few cm across, and ten times that a usual head CT."""
    if not np.all(np.isfinite(sp)) or sp.min() <= 0:
        return
    fov = sp * np.maximum(size - 1, 1)
    small = (fov < MIN_HEAD_FOV_MM) & (sp < CM_SUSPECT_SPACING_MM)
    # in-plane (i, j): both axes together; along the slices (k): alone (a short scan is fine)
    inplane = bool(small[0] and small[1]) or bool(small[2] and fov[2] < 0.5 * MIN_HEAD_FOV_MM)
    if not inplane:
        return
    x10 = sp * 10.0
    raise InputError(
        f"{name}: voxel spacing {' x '.join(f'{v:.3g}' for v in sp)} mm makes the scan "
        f"{' x '.join(f'{v:.0f}' for v in fov)} mm, far too small for a head; ten times that "
        f"({' x '.join(f'{v:.3g}' for v in x10)} mm voxels) is a usual head CT: the spacing was probably written in cm. "
        "DICOM PixelSpacing and slice positions, and NIfTI pixdim, are in mm: correct the header (or export the CT again) "
        "and load it again")


#: Largest magnitude of a Hounsfield value (metal in extended-range CT reaches ~30000 HU).
MAX_ABS_HU = 100_000.0


def _check_hounsfield(arr: np.ndarray, name: str, scale_hint: str = "") -> None:
    """Reject volumes whose values are not Hounsfield units (no air, 8-bit, unscaled 12-bit,
    absurd magnitudes from a wrong rescale). ``scale_hint``: words naming the file's rescale."""
    vmin, vmax = float(np.min(arr)), float(np.max(arr))  # every voxel: one wild value is enough
    if max(abs(vmin), abs(vmax)) > MAX_ABS_HU:
        raise InputError(
            f"{name}: values are not Hounsfield units (from {vmin:.3g} to {vmax:.3g}; a CT spans about -1024 to 3071, "
            f"and up to ~30000 HU for metal){scale_hint or '; is the rescale slope/intercept wrong?'}")
    sample = arr[:: max(1, arr.shape[0] // 32), ::4, ::4]
    if sample.size == 0:
        sample = arr
    lo, hi = np.percentile(sample, [0.5, 99.9])
    if arr.dtype == np.uint8 or (lo >= 0 and hi <= 255):
        raise InputError(f"{name} holds 0..255 values (an 8-bit picture or mask), not CT Hounsfield units")
    if lo > -500:
        raise InputError(
            f"{name} does not look like a CT in Hounsfield units: no air around the head "
            f"(lowest values ~{lo:.0f}, air is -1000 HU){scale_hint or '; is the rescale slope/intercept missing?'}"
        )
    if hi < 200:
        raise InputError(f"{name} does not look like a head CT: no bone or denser values (highest ~{hi:.0f} HU){scale_hint}")


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
            unreadable path (permission: owner, mode and the user we run as); no image in it;
            an unknown ``series``; inconsistent slice geometry; more voxels than the memory
            left holds; NaN/infinite voxels; values that are not Hounsfield units; spacing in
            cm; sheared axes. A NIfTI without orientation loads, with a ``WARNING`` note.
    """
    p = Path(path).expanduser()
    from monotracker.ct.sphere_fit import warm_up_in_background

    warm_up_in_background()  # the fiducial fits compile while the series is read
    try:
        return _load_volume(p, series)
    except PermissionError as exc:
        raise permission_error(Path(exc.filename or p)) from None
    except MemoryError:
        raise InputError(f"{p.name} is too large for this machine's memory: crop it to the head or resample it to a "
                         "coarser grid, or use a machine with more memory") from None


def _load_volume(p: Path, series: str | None) -> Volume:
    notes: list[str] = []
    coverage = Coverage()
    check_readable(p)
    hdr = None
    if p.is_dir():
        img = _read_dicom_folder(p, series, notes, coverage)
    else:
        if p.stat().st_size == 0:
            raise InputError(f"{p.name} is empty (0 bytes)")
        img = None
        if not p.name.lower().endswith(VOLUME_SUFFIXES[:-1]):
            from monotracker.ct.dicom_series import read_dicom

            img = read_dicom(p, series, notes, coverage)  # multi-frame (enhanced) CT; None for other files
        if img is None:
            img, hdr = _read_file(p, notes)
            if series is not None:
                notes.append("series= ignored: the input is a single file")
    name = p.name or str(p)
    img = _check_image(img, name)
    vol = Volume.from_image(img, source=str(p), notes=notes, coverage=coverage)
    hint = scale_hint(hdr)
    if vol.array.dtype.kind == "f":
        bad = int(np.count_nonzero(~np.isfinite(vol.array)))  # every voxel, not a sample
        if bad:
            raise InputError(f"{name} contains {bad} NaN or infinite voxels; its values cannot be trusted{hint}")
    _check_hounsfield(vol.array, name, hint)
    log.info("loaded %s: %s", p, vol.describe())
    return vol
