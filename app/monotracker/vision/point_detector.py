"""A detector that hands over given points: replaying recorded detections, tests, benchmarks.

:class:`PointDetector` has the detectors' interface (``detect(image, hint=None) -> Detection``) but ignores
the image: it returns the ball centres (px) and minor semi-axes (px) set with :meth:`set`. With
it, the pose stream's trust logic runs on point-level scenes with exact ground truth
(``monotracker.sim.scenes``) or on detections recorded elsewhere.
"""

from __future__ import annotations

import numpy as np

from .detection import Detection, ImageFiducial


class PointDetector:
    """``set(points_px (m, 2), minor_axes_px (m,)[, edge_rms_px])`` before each ``detect``;
    with ``edge_rms_px`` (px, one for all or one per point) each ball reports it as its edge
    fit's spread (``features["edge_rms_px"]``), as the edge detector does, and the pose tracker
    covers its centre with it."""

    name = "points"
    #: it reads no image: the pose tracker gives it no mean of a still view's frames
    reads_image = False

    def __init__(self):
        self.points = np.zeros((0, 2))
        self.minor = np.zeros(0)
        self.edge_rms = None

    def set(self, points_px, minor_axes_px, edge_rms_px=None) -> None:
        self.points = np.asarray(points_px, float).reshape(-1, 2)
        self.minor = np.asarray(minor_axes_px, float).reshape(-1)
        self.edge_rms = None if edge_rms_px is None else np.broadcast_to(np.asarray(edge_rms_px, float),
                                                                         (len(self.points),))

    def detect(self, image, hint=None) -> Detection:
        """The points set with :meth:`set` (``image`` and ``hint`` are ignored)."""
        fids = [ImageFiducial(np.array(p, float), (float(b), float(b)), 0.0, 1.0, float(np.pi * b * b),
                              features={} if self.edge_rms is None else {"edge_rms_px": float(self.edge_rms[i])})
                for i, (p, b) in enumerate(zip(self.points, self.minor))]
        return Detection(fids, [], 0.0, self.name)
