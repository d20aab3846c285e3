"""Write CT DICOM series with pydicom the way scanners write them, for tests and benchmarks.

Each slice gets its own ImagePositionPatient / ImageOrientationPatient, so gantry tilt (both
encodings), uneven spacing, missing slices, shuffled instance numbers, interleaved acquisitions
and enhanced multi-frame objects can be written with every pixel's true LPS position known:
pixel (column c, row r) of a slice lies at ``IPP + c * PixelSpacing[1] * row + r * PixelSpacing[0] * col``
(DICOM PS3.3 C.7.6.2.1.1), mm. Pixel values come from ``field(points_lps (n, 3)) -> HU``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

UID_ROOT = "1.2.826.0.1.3680043.8.498."


@dataclass
class SliceSpec:
    """One slice: its IPP (LPS mm) and IOP (row cosines, column cosines)."""

    ipp: np.ndarray
    iop: np.ndarray
    instance: int = 0
    acquisition: int = 1
    #: AcquisitionTime and ContentTime of the slice, s since midnight (None: not written).
    time_s: float | None = None
    #: The patient's displacement for this slice, mm (LPS): ``field`` is sampled at
    #: ``points - shift`` (motion between two acquisitions).
    shift_mm: tuple = (0.0, 0.0, 0.0)


def axial_iop() -> np.ndarray:
    return np.array([1.0, 0, 0, 0, 1.0, 0])


def tilted_iop(tilt_deg: float) -> np.ndarray:
    """Axial plane tilted about the L axis by ``tilt_deg`` (gantry tilt, IOP encoding)."""
    t = np.radians(tilt_deg)
    return np.array([1.0, 0, 0, 0, np.cos(t), np.sin(t)])


def stack_specs(z_mm, iop=None, origin=(0.0, 0.0, 0.0), shear_y_per_mm: float = 0.0) -> list[SliceSpec]:
    """Slices at table positions ``z_mm`` (S, mm): IPP = origin + (0, shear * z, z)."""
    iop = axial_iop() if iop is None else np.asarray(iop, float)
    o = np.asarray(origin, float)
    return [SliceSpec(o + np.array([0.0, shear_y_per_mm * z, z]), iop, k + 1) for k, z in enumerate(z_mm)]


def pixel_points(spec: SliceSpec, rows: int, cols: int, pixel_spacing: tuple[float, float]) -> np.ndarray:
    """(rows, cols, 3) true LPS positions of a slice's pixels, mm."""
    row, col = spec.iop[:3], spec.iop[3:]
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    return spec.ipp + (c[..., None] * pixel_spacing[1]) * row + (r[..., None] * pixel_spacing[0]) * col


def _base_dataset(series_uid: str, description: str, rows: int, cols: int, sop_class: str):
    import pydicom
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = generate_uid(prefix=UID_ROOT)
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = pydicom.Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = "CT"
    ds.PatientName = "PHANTOM^HEAD"
    ds.PatientID = "PHANTOM"
    ds.StudyInstanceUID = UID_ROOT + "1"
    ds.FrameOfReferenceUID = UID_ROOT + "2"  # one scan (type 1 in the CT image IOD: scanners always write it)
    ds.ImageType = ["ORIGINAL", "PRIMARY", "AXIAL"]
    ds.SeriesInstanceUID = series_uid
    ds.SeriesDescription = description
    ds.Rows, ds.Columns = rows, cols
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
    return ds


def write_series(folder: Path, specs: list[SliceSpec], field, rows: int = 32, cols: int = 32,
                 pixel_spacing: tuple[float, float] = (1.0, 1.0), series_uid: str | None = None,
                 description: str = "synthetic", intercept: float = -1024.0) -> list[Path]:
    """One single-frame CT file per slice; returns the paths (in ``specs`` order)."""
    from pydicom.uid import CTImageStorage, generate_uid

    folder.mkdir(parents=True, exist_ok=True)
    series_uid = series_uid or generate_uid(prefix=UID_ROOT)
    paths = []
    for k, spec in enumerate(specs):
        ds = _base_dataset(series_uid, description, rows, cols, CTImageStorage)
        ds.ImagePositionPatient = [f"{x:.6f}" for x in spec.ipp]
        ds.ImageOrientationPatient = [f"{x:.8f}" for x in spec.iop]
        ds.PixelSpacing = [f"{x:.6f}" for x in pixel_spacing]
        ds.SliceThickness = "1.0"
        ds.InstanceNumber = spec.instance or k + 1
        ds.AcquisitionNumber = spec.acquisition
        if spec.time_s is not None:
            t = float(spec.time_s)
            ds.AcquisitionTime = ds.ContentTime = f"{int(t // 3600):02d}{int(t % 3600 // 60):02d}{t % 60:09.6f}"
        ds.RescaleSlope, ds.RescaleIntercept = 1, intercept
        pts = pixel_points(spec, rows, cols, pixel_spacing).reshape(-1, 3) - np.asarray(spec.shift_mm, float)
        hu = field(pts).reshape(rows, cols)
        ds.PixelData = np.clip(np.rint(hu - intercept), -32768, 32767).astype("<i2").tobytes()
        p = folder / f"{description}_{k:04d}.dcm"
        ds.save_as(p, enforce_file_format=True)
        paths.append(p)
    return paths


def write_enhanced(path: Path, specs: list[SliceSpec], field, rows: int = 32, cols: int = 32,
                   pixel_spacing: tuple[float, float] = (1.0, 1.0), description: str = "enhanced",
                   intercept: float = -1024.0) -> Path:
    """One enhanced (multi-frame) CT object holding every slice as a frame, per-frame positions
    in PerFrameFunctionalGroupsSequence, orientation / spacing / rescale shared."""
    import pydicom
    from pydicom.uid import EnhancedCTImageStorage, generate_uid

    ds = _base_dataset(generate_uid(prefix=UID_ROOT), description, rows, cols, EnhancedCTImageStorage)
    ds.NumberOfFrames = len(specs)
    ds.InstanceNumber = 1
    shared = pydicom.Dataset()
    po = pydicom.Dataset()
    po.ImageOrientationPatient = [f"{x:.8f}" for x in specs[0].iop]
    pm = pydicom.Dataset()
    pm.PixelSpacing = [f"{x:.6f}" for x in pixel_spacing]
    pm.SliceThickness = "1.0"
    pv = pydicom.Dataset()
    pv.RescaleSlope, pv.RescaleIntercept, pv.RescaleType = 1, intercept, "HU"
    shared.PlaneOrientationSequence = [po]
    shared.PixelMeasuresSequence = [pm]
    shared.PixelValueTransformationSequence = [pv]
    ds.SharedFunctionalGroupsSequence = [shared]
    frames, per = [], []
    for spec in specs:
        item = pydicom.Dataset()
        pp = pydicom.Dataset()
        pp.ImagePositionPatient = [f"{x:.6f}" for x in spec.ipp]
        item.PlanePositionSequence = [pp]
        per.append(item)
        hu = field(pixel_points(spec, rows, cols, pixel_spacing).reshape(-1, 3)).reshape(rows, cols)
        frames.append(np.clip(np.rint(hu - intercept), -32768, 32767).astype("<i2"))
    ds.PerFrameFunctionalGroupsSequence = per
    ds.PixelData = np.stack(frames).tobytes()
    path.parent.mkdir(parents=True, exist_ok=True)
    ds.save_as(path, enforce_file_format=True)
    return path


#: HU per mm of the linear test fields of :func:`known_point_errors`.
FIELD_HU_PER_MM = 80.0


def known_point_errors(write, load, specs: list[SliceSpec], points_lps: np.ndarray, rows: int = 32, cols: int = 32,
                       pixel_spacing: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """3D position error (n, 3), mm, of known LPS points after writing and loading a series.

    Three series are written with ``write(field) -> path`` (fields linear in L, P and S in turn,
    :data:`FIELD_HU_PER_MM`, -1000 HU at the lowest pixel); each is loaded with ``load(path) ->
    Volume`` and sampled (trilinear) at ``points_lps``; a linear field is interpolated exactly by
    a right geometry, so the value read back gives the point's coordinate as the loaded volume
    places it. Rounding to integer HU limits the resolution to ~0.006 mm.
    """
    from scipy.ndimage import map_coordinates

    all_px = np.concatenate([pixel_points(s, rows, cols, pixel_spacing).reshape(-1, 3) for s in specs])
    lo = all_px.min(axis=0)
    err = np.zeros((len(points_lps), 3))
    for a in range(3):
        def field(p, a=a):
            return -1000.0 + FIELD_HU_PER_MM * (p[:, a] - lo[a])

        vol = load(write(field))
        idx = vol.lps_to_index(points_lps)[:, ::-1].T  # (k, j, i)
        val = map_coordinates(vol.array.astype(np.float64), idx, order=1, mode="nearest")
        err[:, a] = (val + 1000.0) / FIELD_HU_PER_MM + lo[a] - points_lps[:, a]
    return err


# ------------------------------------------------------------------ scenes at the scan's edges
def specs_along(iop_rot: np.ndarray, steps_mm: np.ndarray) -> list[SliceSpec]:
    """Slices of orientation ``iop_rot`` (3x3; columns: row and column cosines, LPS) at
    positions that start at the origin and advance by ``steps_mm`` ((n-1, 3), LPS mm): gantry
    tilt in either encoding, shear, uneven spacing and gaps are all a choice of steps."""
    iop = np.r_[iop_rot[:, 0], iop_rot[:, 1]]
    pos = np.vstack([np.zeros(3), np.cumsum(np.asarray(steps_mm, float), axis=0)])
    return [SliceSpec(p, iop, k + 1) for k, p in enumerate(pos)]


def acquisition_solid(specs: list[SliceSpec], rows: int, cols: int, pixel_spacing: tuple[float, float]):
    """Origin (LPS mm) and the three edge vectors (3x3, columns: along a row, along a column,
    first to last slice position) of the acquired solid, a parallelepiped for a straight stack
    (its corners are the first and last slices' corner pixels)."""
    row, col = specs[0].iop[:3], specs[0].iop[3:]
    E = np.column_stack([(cols - 1) * pixel_spacing[1] * row, (rows - 1) * pixel_spacing[0] * col,
                         specs[-1].ipp - specs[0].ipp])
    return specs[0].ipp, E


def points_inset(specs: list[SliceSpec], inset_mm: float, rows: int, cols: int,
                 pixel_spacing: tuple[float, float], where: str = "corners") -> np.ndarray:
    """Points ``inset_mm`` inside every face of the acquired solid (LPS mm): its 8 corners
    (``where="corners"``) or the middles of 4 of its 12 edges (``"edges"``)."""
    o, E = acquisition_solid(specs, rows, cols, pixel_spacing)
    frac = []
    for a in range(3):
        n = np.cross(E[:, (a + 1) % 3], E[:, (a + 2) % 3])
        frac.append(inset_mm / abs(E[:, a] @ n / np.linalg.norm(n)))
    if where == "corners":
        ab = [(x, y, z) for x in (frac[0], 1 - frac[0]) for y in (frac[1], 1 - frac[1]) for z in (frac[2], 1 - frac[2])]
    else:
        ab = [(0.5, frac[1], frac[2]), (1 - frac[0], 0.5, 1 - frac[2]), (frac[0], 1 - frac[1], 0.5),
              (0.5, 1 - frac[1], 1 - frac[2])]
    return np.array([o + E @ np.array(s) for s in ab])


def ball_field(centres_lps, radius_mm: float, air_centre_lps, ball_hu: float = 2500.0,
               tissue_hu: float = 20.0, edge_sigma_mm: float = 0.5, air_radius_mm: float = 8.0):
    """A ``field`` for :func:`write_series`: soft tissue (``tissue_hu``) with a pocket of air
    (so the volume reads as a CT) and balls of ``radius_mm`` at ``centres_lps`` whose edge is
    blurred by a Gaussian of ``edge_sigma_mm`` (the scanner's point spread), HU."""
    from scipy.special import erfc

    centres = np.atleast_2d(np.asarray(centres_lps, float))
    air = np.asarray(air_centre_lps, float)

    def field(p):
        v = np.full(len(p), tissue_hu)
        v[np.linalg.norm(p - air, axis=1) < air_radius_mm] = -1000.0
        for c in centres:
            d = np.linalg.norm(p - c, axis=1) - radius_mm
            v += (ball_hu - tissue_hu) * 0.5 * erfc(d / (np.sqrt(2.0) * edge_sigma_mm))
        return v
    return field
