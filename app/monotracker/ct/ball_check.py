"""Is there a fiducial ball at a point the operator picked in the CT? (issue 36)

An operator-added fiducial is "verified" only when the CT holds a ball there that the detection
itself would accept: a dense blob that stands alone (not part of the skull, a bone edge or
metal), is round, fits a blurred sphere of about the given radius, is not cut by the edge of the
scan, and whose fitted centre is near the point picked. A mean-contrast test (mean HU inside
against a shell around) is not enough: a point inside the 7 mm skull reads ~1200 HU inside and
less around (diploe, scalp, brain) and passed as a "verified ball".

The blob is taken at rising thresholds (half the contrast of the densest voxel near the point up
to 85 % of it, as :mod:`.blob_search`'s ladder does), so a ball resting on bone, joined to it at
the lowest level, separates higher up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from monotracker.ct.volume import Volume

#: Thresholds tried between 50 % and 85 % of the point's contrast over soft tissue.
LEVELS = 6
#: The fitted radius may differ from the given one by this fraction.
RADIUS_TOLERANCE = 0.2
#: Smallest contrast (HU over soft tissue) of a ball's densest voxel.
MIN_CONTRAST_HU = 300.0


@dataclass(frozen=True)
class BallCheck:
    """``verified``: a ball is there; ``centre_lps`` its fitted centre (LPS mm, None when not
    verified); ``radius_mm`` its fitted radius; ``why`` one line for the operator."""

    verified: bool
    why: str
    centre_lps: np.ndarray | None = None
    radius_mm: float = float("nan")
    #: The ball around the point does not lie inside the CT volume (nothing to check it against).
    outside: bool = False


def check_ball_at(volume: Volume, centre_lps, radius_mm: float, levels: dict,
                  min_contrast_hu: float = MIN_CONTRAST_HU) -> BallCheck:
    """Whether the CT holds a fiducial ball of ``radius_mm`` (mm) at ``centre_lps`` (LPS mm):
    see the module docstring. ``levels``: the scan's grey levels (``tissue``, ``noise``,
    ``air``, HU; :func:`~.levels.estimate_levels`); ``min_contrast_hu`` the least HU over soft
    tissue of the densest voxel near the point. The fitted centre must lie within half the
    radius (at least 1 mm) of the point."""
    from monotracker.ct.coverage import pad_value
    from monotracker.ct.fiducials import _fit_blob
    from monotracker.ct.kit import FiducialKit

    c = np.asarray(centre_lps, float)
    r = float(radius_mm)
    sp = volume.spacing_mm
    arr = volume.array
    shape = np.array(arr.shape)
    reach = r + 6.0  # mm: the ball, its blurred edge and the fit's window
    ijk = volume.lps_to_index(c[None])[0]
    half = np.ceil(reach / sp).astype(int)
    lo = np.maximum(np.floor(ijk).astype(int) - half, 0)[::-1]  # k, j, i
    hi = np.minimum(np.ceil(ijk).astype(int) + half + 1, np.array(volume.size_ijk))[::-1]
    if np.any(hi - lo < 3):
        return BallCheck(False, "the ball is not inside the CT volume", outside=True)
    sub = arr[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    # the densest voxel within half the radius of the point: the ball's core if there is one
    grid = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), axis=-1)
    dist = np.linalg.norm(volume.zyx_to_lps(grid.reshape(-1, 3)) - c, axis=1).reshape(sub.shape)
    core = dist <= max(0.5 * r, float(sp.max()))
    if not core.any():
        return BallCheck(False, "the ball is not inside the CT volume", outside=True)
    tissue = float(levels.get("tissue", 0.0))
    vals = np.where(core, sub, -np.inf)
    seed = np.unravel_index(int(np.argmax(vals)), sub.shape)
    peak = float(sub[seed])
    if peak - tissue < min_contrast_hu:
        return BallCheck(False, f"no dense ball of radius {r:g} mm there in the CT (densest {peak:.0f} HU near the point, "
                                f"soft tissue {tissue:.0f} HU)")
    pad_hu = pad_value(volume, float(np.min(sub)))
    kit = FiducialKit(radius_mm=r)
    why = ""
    for frac in np.linspace(0.5, 0.85, LEVELS):
        T = tissue + frac * (peak - tissue)
        labels, _ = ndimage.label(sub > T, structure=np.ones((3, 3, 3), bool))
        comp = labels == labels[seed]
        kji = np.argwhere(comp)
        runs_on = np.any((kji.min(axis=0) == 0) & (lo > 0)) or np.any((kji.max(axis=0) == np.array(sub.shape) - 1) & (hi < shape))
        if runs_on:
            why = (f"no ball of radius {r:g} mm there: the dense region at the point runs on more than {reach:.0f} mm "
                   "(bone, the skull, metal?)")
            continue  # joined to something larger: it may separate higher up
        cand, rej = _fit_blob(volume, kji + lo, T, [], levels, kit, pad_hu)
        if cand is None:
            why = f"no fiducial ball there: {rej.reason}"
            continue
        rf = float(cand["r"])
        if abs(rf - r) > RADIUS_TOLERANCE * r:
            why = f"the ball there has radius {rf:.2f} mm, not {r:g} mm"
            continue
        off = float(np.linalg.norm(cand["c"] - c))
        if off > max(0.5 * r, 1.0):
            return BallCheck(False, f"the ball nearest the point is centred {off:.1f} mm away: pick its centre")
        return BallCheck(True, f"a ball of radius {rf:.2f} mm fits the CT there ({off:.2f} mm from the point, "
                               f"{peak:.0f} HU)", np.asarray(cand["c"], float), rf)
    return BallCheck(False, why or f"no ball of radius {r:g} mm there in the CT")


__all__ = ["BallCheck", "check_ball_at"]
