"""CT: loading volumes, detecting the sphere fiducials, the head's skin surface (LPS mm)."""

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
