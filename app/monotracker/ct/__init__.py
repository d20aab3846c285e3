"""CT: loading volumes, detecting the sphere fiducials, the head's skin surface (LPS mm)."""
from typing import TYPE_CHECKING

from monotracker._lazy import lazy_exports

if TYPE_CHECKING:  # the names below, imported on first use (monotracker/_lazy.py: a fast CLI start)
    from monotracker.ct.fiducials import (
        Fiducial,
        FiducialDetection,
        RejectedBlob,
        detect_fiducials,
        detect_fiducials_paper,
        estimate_levels,
    )
    from monotracker.ct.dicom_series import SeriesInfo, list_series
    from monotracker.ct.kit import FiducialKit
    from monotracker.ct.surface import head_surface
    from monotracker.ct.volume import Volume, load_volume

__all__ = [
    "Fiducial",
    "FiducialDetection",
    "FiducialKit",
    "RejectedBlob",
    "SeriesInfo",
    "Volume",
    "detect_fiducials",
    "detect_fiducials_paper",
    "estimate_levels",
    "head_surface",
    "list_series",
    "load_volume",
]

__getattr__, __dir__ = lazy_exports(__name__, {
    "Fiducial": "monotracker.ct.fiducials",
    "FiducialDetection": "monotracker.ct.fiducials",
    "RejectedBlob": "monotracker.ct.fiducials",
    "detect_fiducials": "monotracker.ct.fiducials",
    "detect_fiducials_paper": "monotracker.ct.fiducials",
    "estimate_levels": "monotracker.ct.fiducials",
    "SeriesInfo": "monotracker.ct.dicom_series",
    "list_series": "monotracker.ct.dicom_series",
    "FiducialKit": "monotracker.ct.kit",
    "head_surface": "monotracker.ct.surface",
    "Volume": "monotracker.ct.volume",
    "load_volume": "monotracker.ct.volume",
})
