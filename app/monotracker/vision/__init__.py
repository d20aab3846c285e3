"""vision: frame sources, camera model and calibration, fiducial detectors, pose stream.

Public API (see docs/vision.md):
* :mod:`.frames`: ``Frame``, ``FrameSource``, ``OpenCVCamera``, ``VideoFileSource``,
  ``ImageFolderSource``, ``open_source``, ``FrameWatchdog``, ``CameraDisconnected``;
  the simulator is :class:`monotracker.sim.camera_sim.SimulatedCamera`.
* :mod:`.camera_model`: ``CameraModel`` (K, dist, image_size; load/save OpenCV YAML / JSON).
* :mod:`.detect_classical`: ``ClassicalDetector``; :mod:`.detect_learned`: ``LearnedDetector``;
  both return :class:`.detection.Detection` (centres px, axes px, angle, score).
* :mod:`.pose_stream`: ``PoseStream`` and ``PoseEstimate`` (the per-frame ``PoseTracker``
  lives in :mod:`.pose_tracker`, re-exported by :mod:`.pose_stream`).
"""
from typing import TYPE_CHECKING

from monotracker._lazy import lazy_exports

if TYPE_CHECKING:  # the names below, imported on first use (monotracker/_lazy.py: a fast CLI start)
    from .camera_model import CameraModel, default_camera
    from .detection import Detection, ImageFiducial
    from .frames import (CameraDisconnected, Frame, FrameSource, FrameWatchdog, ImageFolderSource, OpenCVCamera,
                         VideoFileSource, open_source)

__all__ = ["CameraModel", "default_camera", "Detection", "ImageFiducial", "CameraDisconnected", "Frame",
           "FrameSource", "FrameWatchdog", "ImageFolderSource", "OpenCVCamera", "VideoFileSource", "open_source"]

__getattr__, __dir__ = lazy_exports(__name__, {
    "CameraModel": ".camera_model",
    "default_camera": ".camera_model",
    "Detection": ".detection",
    "ImageFiducial": ".detection",
    "CameraDisconnected": ".frames",
    "Frame": ".frames",
    "FrameSource": ".frames",
    "FrameWatchdog": ".frames",
    "ImageFolderSource": ".frames",
    "OpenCVCamera": ".frames",
    "VideoFileSource": ".frames",
    "open_source": ".frames",
})
