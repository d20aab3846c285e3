"""The checked geometry of one DICOM series: slices sorted along the normal, then regular,
resampled (tilt, uneven spacing, a few missing slices) or refused (see
:mod:`monotracker.ct.dicom_series`). Positions are LPS mm."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monotracker.ct.dicom_headers import _Slice
from monotracker.ct.dicom_interleave import check_interleaved
from monotracker.errors import InputError

#: Largest number of consecutive missing slices interpolated across; a larger gap is refused.
MAX_MISSING_SLICES = 2
#: Relative spread of slice gaps still read as one uniform spacing.
SPACING_RTOL = 0.01
#: Absolute tolerance on positions (mm): DICOM writes IPP as decimal strings.
POS_ATOL_MM = 0.01
#: Largest difference between two slices' direction cosines still read as one orientation.
IOP_ATOL = 1e-3


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
    #: Slabs along the normal between two slices with slices missing between them (interpolated
    #: across on loading): (d_lo, d_hi) mm and the number of slices missing.
    missing: list = field(default_factory=list)

    @property
    def positions(self) -> np.ndarray:
        """(n, 3) ImagePositionPatient of the slices, LPS mm, in ``d`` order."""
        return np.array([s.position for s in self.slices], float)


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
        for (_a0, a1), (b0, _b1) in zip(ranges, ranges[1:]):
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
    missing = []
    if not regular_spacing and gapped.any():
        missing = [(float(dd[i]), float(dd[i + 1]), int(round(ratio[i])) - 1) for i in np.flatnonzero(gapped)]
    spacing = np.array([slices[0].pixel_spacing[1], slices[0].pixel_spacing[0], step], float)
    return _Geometry(slices, row, col, normal, dd, off, spacing, tilt_deg, bool(regular_spacing and tilt_deg == 0.0), notes,
                     missing)
