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
from .detection import BlobRules, Detection, DetectionHint, ImageFiducial, analyse_blobs, blob_contours


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
    #: the edge blur (px) measured in the last full-frame search, reused by windowed searches
    _blur_px: float | None = field(default=None, init=False, repr=False, compare=False)

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
        """Balls in ``image`` (BGR uint8, the camera's full frame). ``hint``: the balls'
        predicted ellipses (:class:`~.detection.DetectionHint`): only windows around them are
        searched (:func:`search_windows`); None: the whole frame. The edge blur measured in the
        last full-frame search is reused in windowed searches (optics change slowly; a window
        search measures it itself when none is known)."""
        t0 = time.perf_counter()
        info: dict = {}
        windowed = hint is not None and len(hint) > 0
        if not windowed:
            mask = self.mask(image)
            t_mask = time.perf_counter() - t0
            accepted, rejected = analyse_blobs(image, mask, self.rules, self.name,
                                               centre_method=self.centre_method, info=info)
            if info.get("edge_blur_px") is not None:
                self._blur_px = info["edge_blur_px"]
        else:
            contours, cut = self._window_contours(image, hint)
            t_mask = time.perf_counter() - t0
            accepted, rejected = analyse_blobs(image, None, self.rules, self.name, centre_method=self.centre_method,
                                               edge_blur_px=self._blur_px, contours=contours, info=info)
            rejected += cut
            if self._blur_px is None and info.get("edge_blur_px") is not None:
                self._blur_px = info["edge_blur_px"]
        stages = {"mask": t_mask, **info.get("stages_s", {})}
        return Detection(accepted, rejected, time.perf_counter() - t0, self.name, stages_s=stages, windowed=windowed)

    def _window_contours(self, image: np.ndarray, hint: DetectionHint) -> tuple[list, list]:
        """(contours in image px of the ball-coloured blobs inside the hint's windows, rejected
        :class:`ImageFiducial` records of blobs that extend beyond their window even after it
        was grown once)."""
        h, w = image.shape[:2]
        boxes = search_windows(hint, (h, w))
        grow = 2.0 * self.rules.radius_range_px[1]
        for attempt in range(2):
            contours, cut_boxes, cut = self._contours_in(image, boxes)
            if not cut_boxes or attempt == 1:
                break
            boxes = [_grown(b, grow, (h, w)) if i in cut_boxes else b for i, b in enumerate(boxes)]
        rejected = []
        for cnt in cut:
            x, y, bw, bh = cv2.boundingRect(cnt)
            rejected.append(ImageFiducial(np.array([x + bw / 2, y + bh / 2]), (bw / 2, bh / 2), 0.0, 0.0,
                                          float(cv2.contourArea(cnt)),
                                          "extends beyond its search window (larger than a ball?)"))
        return contours, rejected

    def _contours_in(self, image: np.ndarray, boxes: list) -> tuple[list, set, list]:
        """Blobs of the colour mask inside ``boxes`` (x0, y0, x1, y1 px): (whole contours,
        indices of the boxes a blob leaves through an edge that is not the image's, those
        blobs' contours)."""
        h, w = image.shape[:2]
        if not boxes:
            return [], set(), []
        b = np.array(boxes)
        X0, Y0, X1, Y1 = int(b[:, 0].min()), int(b[:, 1].min()), int(b[:, 2].max()), int(b[:, 3].max())
        mask = np.zeros((Y1 - Y0, X1 - X0), np.uint8)
        inner = np.zeros_like(mask)          # window pixels that are not on a window's inner edge
        for x0, y0, x1, y1 in boxes:
            sub = self.mask(image[y0:y1, x0:x1])
            np.maximum(mask[y0 - Y0:y1 - Y0, x0 - X0:x1 - X0], sub, out=mask[y0 - Y0:y1 - Y0, x0 - X0:x1 - X0])
            ix0, iy0 = x0 + (x0 > 0), y0 + (y0 > 0)
            ix1, iy1 = x1 - (x1 < w), y1 - (y1 < h)
            inner[iy0 - Y0:iy1 - Y0, ix0 - X0:ix1 - X0] = 1
        whole, cut, cut_boxes = [], [], set()
        for cnt in blob_contours(mask, (X0, Y0)):
            pts = cnt.reshape(-1, 2)
            if inner[pts[:, 1] - Y0, pts[:, 0] - X0].all():
                whole.append(cnt)
                continue
            cut.append(cnt)
            x, y, bw, bh = cv2.boundingRect(cnt)
            for i, (x0, y0, x1, y1) in enumerate(boxes):
                if x < x1 and x + bw > x0 and y < y1 and y + bh > y0:
                    cut_boxes.add(i)
        return whole, cut_boxes, cut


#: a search window reaches beyond a ball's predicted ellipse by this much (px) + this share of
#: its semi-major axis, + per frame of the hint's age beyond the first: the head's motion between
#: frames (up to ~50 mm/s: ~3.5 px per frame at 0.5 m with f = 1100 px) and the prediction's
#: error. A ball that moved on the skin by more is found by the next full-frame search.
WINDOW_MARGIN_PX = 8.0
WINDOW_MARGIN_PER_RADIUS = 0.5
WINDOW_MARGIN_PER_AGE_PX = 6.0


def search_windows(hint: DetectionHint, shape) -> list:
    """The image windows (x0, y0, x1, y1) px, clipped to the image of ``shape`` (h, w), that
    cover the hint's predicted balls with their margins (:data:`WINDOW_MARGIN_PX`);
    overlapping windows are merged into their bounding box."""
    h, w = shape[:2]
    boxes = []
    for (cx, cy), (a, _b) in zip(hint.centres_px, hint.axes_px):
        half = a + WINDOW_MARGIN_PX + WINDOW_MARGIN_PER_RADIUS * a + WINDOW_MARGIN_PER_AGE_PX * (hint.age_frames - 1)
        if not (np.isfinite(cx) and np.isfinite(cy) and np.isfinite(half)):
            continue
        x0, y0 = max(int(np.floor(cx - half)), 0), max(int(np.floor(cy - half)), 0)
        x1, y1 = min(int(np.ceil(cx + half)) + 1, w), min(int(np.ceil(cy + half)) + 1, h)
        if x1 - x0 >= 3 and y1 - y0 >= 3:
            boxes.append((x0, y0, x1, y1))
    return _merged(boxes)


def _merged(boxes: list) -> list:
    """Boxes (x0, y0, x1, y1) with every overlapping pair replaced by its bounding box."""
    boxes = list(boxes)
    merged = True
    while merged:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    boxes[i] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return boxes


def _grown(box, by: float, shape) -> tuple:
    """``box`` (x0, y0, x1, y1) grown by ``by`` px on every side, clipped to the image (h, w)."""
    h, w = shape[:2]
    g = int(np.ceil(by))
    return (max(box[0] - g, 0), max(box[1] - g, 0), min(box[2] + g, w), min(box[3] + g, h))
