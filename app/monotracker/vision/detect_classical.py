"""Classical fiducial detector: HSV green threshold, contours, ellipse fit, sub-pixel centre.

Pipeline (choices written down; the paper uses a learned YOLOv8-seg instead):
1. BGR -> HSV; a pixel is "ball coloured" (by default green; any :class:`BallColour`, e.g.
   learned from a click, via ``colour=``/:meth:`ClassicalDetector.set_colour`) when hue is in [``hue_lo``, ``hue_hi``] (OpenCV's
   0-180 scale; 35-90 covers the matte green dye under warm and cold light), saturation
   >= ``sat_min`` and value >= ``val_min``. Skin, blue drapes, gloves and steel fail this test.
2. A 3x3 opening removes single-pixel speckle (sensor noise).
3. External contours; each blob is scored and refined by :func:`~.detection.analyse_blobs`
   (ellipse fit residual, roundness, fill, plausible size for the ball radius at 0.25-1 m,
   size consensus), sub-pixel centre from the soft chromaticity mask.
Cost at 1280x720: ~3-5 ms on one core (the threshold dominates).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from .ball_colour import BallColour
from .detection import BlobRules, Detection, DetectionHint, analyse_blobs


@dataclass
class ClassicalDetector:
    """HSV-threshold ball detector. ``rules`` sets the ball radius (mm), focal length (px)
    and plausibility limits; ``detect(image) -> Detection``."""

    rules: BlobRules = field(default_factory=BlobRules)
    hue_lo: int = 35
    hue_hi: int = 90
    sat_min: int = 90
    val_min: int = 35
    name: str = "classical"
    #: sub-pixel centre: "edge" (edge unmixing + ellipse fit) or "chroma" (the old soft centroid)
    centre_method: str = "edge"
    #: the balls' colour band; None = the four fields above (default green). Set by
    #: :meth:`set_colour` (e.g. learned from a click, or loaded with the camera calibration).
    colour: BallColour | None = None

    def __post_init__(self):
        if self.colour is not None:
            self.set_colour(self.colour)

    def set_colour(self, colour: BallColour) -> None:
        """Threshold ``colour`` from now on (hue band may wrap through 0 for red balls)."""
        self.colour = colour
        self.hue_lo, self.hue_hi, self.sat_min, self.val_min = (colour.hue_lo, colour.hue_hi, colour.sat_min,
                                                                 colour.val_min)

    def mask(self, image: np.ndarray) -> np.ndarray:
        """Binary uint8 mask (0/255) of ball-coloured pixels."""
        band = BallColour(self.hue_lo, self.hue_hi, self.sat_min, self.val_min)
        return cv2.morphologyEx(band.mask(image), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))

    def detect(self, image: np.ndarray, hint: DetectionHint | None = None) -> Detection:
        """Balls in ``image`` (BGR uint8). ``hint``: the balls' predicted ellipses
        (:class:`~.detection.DetectionHint`) or None; (this step: always a full-frame search)."""
        t0 = time.perf_counter()
        accepted, rejected = analyse_blobs(image, self.mask(image), self.rules, self.name,
                                           centre_method=self.centre_method)
        return Detection(accepted, rejected, time.perf_counter() - t0, self.name)
