"""The camera rigs' part of the accuracy verification (``engine/verification.py``): the detector
that keeps each frame's blobs, and the plan's validation fiducials checked on every estimate."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class KeepDetections:
    """The detector the pose tracker uses by default (classical, same rules), remembering the last
    frame's blob centres (px) so that validation fiducials, which the fit ignores, can be found
    (the pose tracker puts them in the detector's hint: ``PoseTracker(watch_ct=...)``), and the
    share of the image covered by ball-coloured areas too large for a ball (``colour_share``,
    0-1; :func:`~monotracker.vision.detection.oversized_colour_share`), as of the last
    full-frame search (a search of windows around the predicted balls cannot measure it)."""

    def __init__(self, K: np.ndarray, radius_mm: float):
        from monotracker.vision.detect_classical import ClassicalDetector
        from monotracker.vision.detection import BlobRules

        self.inner = ClassicalDetector(BlobRules(radius_mm=radius_mm, focal_px=float(np.asarray(K)[0, 0])))
        self.last = np.zeros((0, 2))
        self.colour_share = 0.0

    def detect(self, image, hint=None):
        from monotracker.vision.detection import oversized_colour_share

        det = self.inner.detect(image, hint)
        self.last = np.asarray(det.centres, float).reshape(-1, 2)
        if hint is None or hint.search_all:
            self.colour_share = oversized_colour_share(det, self.inner.rules, image.shape)
        return det

    def __getattr__(self, name):
        return getattr(self.inner, name)


@dataclass
class ValidationSet:
    """The plan's validation fiducials for one camera rig: ``ids``, ``centres_ct`` (m, 3) LPS mm."""

    ids: list
    centres_ct: np.ndarray
    radius_mm: float
    limit_mm: float

    @classmethod
    def from_plan(cls, plan, radius_mm: float, limit_mm: float = 1.5) -> "ValidationSet":
        """(The rig factory sets ``limit_mm`` from ``SessionConfig.max_validation_tre_mm``.)"""
        fs = plan.validation_fiducials()
        return cls([f.id for f in fs], np.array([f.centre_lps_mm for f in fs], float).reshape(-1, 3),
                   float(radius_mm), float(limit_mm))

    def check(self, T_cam_ct, detections_px, used_px, K, dist):
        """ValidationResult for this frame, or None (no validation fiducials, or no pose)."""
        if not self.ids or T_cam_ct is None:
            return None
        from monotracker.registration.validation import validate

        return validate(np.asarray(T_cam_ct, float), self.ids, self.centres_ct, detections_px, K, dist,
                        self.radius_mm, self.limit_mm, used_px=used_px)
