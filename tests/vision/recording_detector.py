"""A test helper: the pose tracker's detector with every Detection it returned kept (the tracker
hands it its hint, as in the product)."""

from __future__ import annotations


class RecordingDetector:
    """Wraps a detector (``rules`` shared, so the tracker gives it the camera's outlines); ``log``
    holds every Detection in order."""

    def __init__(self, det):
        self.det, self.rules, self.log = det, det.rules, []

    def detect(self, image, hint=None):
        d = self.det.detect(image) if hint is None else self.det.detect(image, hint)
        self.log.append(d)
        return d
