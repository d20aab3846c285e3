"""A detector that keeps what it found: every :class:`~.detection.Detection` a pose tracker got
from it, in order, for judging them against a scene's truth afterwards or replaying them through
other trust rules (benchmarks, tests, training scripts)."""

from __future__ import annotations


class RecordingDetector:
    """Wraps a detector; ``log`` holds every Detection it returned, in order. Its ``rules`` are
    the wrapped detector's own (None when it has none), so that the pose tracker gives the
    detector the camera's ball outlines as in the product; the tracker's hint is passed on."""

    def __init__(self, det):
        self.det, self.log = det, []
        self.rules = getattr(det, "rules", None)
        self.reads_image = getattr(det, "reads_image", True)
        if hasattr(det, "reads"):
            self.reads = det.reads      # what it reads of a frame (the still-view mean keeps only that)

    def detect(self, image, hint=None):
        d = self.det.detect(image) if hint is None else self.det.detect(image, hint)
        self.log.append(d)
        return d
