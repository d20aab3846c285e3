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
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from . import edge_fit, edge_kernels
from .ball_colour import BallColour, band_of_balls
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
    #: a learned correction of each accepted ball's centre for its shading
    #: (:class:`~.centre_refiner.CentreRefiner`, issue 28); None = the edge fit's centre as it is
    refiner: object | None = None
    #: a second look at the rejected blobs with the balls' own hue (:meth:`_narrowed_pass`; issue
    #: 28). A drape of a neighbouring hue inside the default band (teal beside green balls)
    #: merges with a ball that touches it into one blob that is no ball, or bends its outline;
    #: thresholded with the hue band of the balls this frame found (or an earlier frame of the
    #: stream), they part. Only rejected blobs are looked at again, with the first pass's checks;
    #: the balls it accepted stay. Rendered tuning sets: whole balls found +4-8 %; alone it let
    #: more 4-5-ball poses be trusted 1-2 mm off (2 -> 4); with the tracker's few-ball cover
    #: (``TrackerConfig.few_balls_cover``), against the previous default: trusted frames 79 -> 94,
    #: 1-2 mm off 2 -> 1, scenes trusted within 1 mm after 8 frames 13 -> 14 of 96 (docs/vision.md).
    #: While tracking only inside the search windows. False = the first pass only
    narrow_second_pass: bool = True
    #: the blob score a blob of the second look needs (None: the first pass's, ``rules.min_score``
    #: 0.5). A ball parted from a drape of a neighbouring hue keeps a notch in its mask where its
    #: rim blended into the drape's colour, so its mask's boundary can score low though the ball
    #: is whole (one planner-placed tuning ball: 0.44); the edge fit and its cut test still judge
    #: it. Opt-in (docs/vision.md, "The second look's blob score"): 0.35 was chosen on the tuning
    #: sets (trusted frames 94 -> 102, scenes trusted within 1 mm after 8 frames 14 -> 17 of 96,
    #: partly hidden balls accepted 6 -> 9), then the held-out sets showed no gain (scenes 35 -> 34
    #: of 177) and more partly hidden balls accepted (56 -> 67): not the default
    narrow_min_score: float | None = None
    #: a third look, in blurred frames, at the blobs both passes rejected: the colour mask
    #: thresholded on a copy of the frame smoothed by a Gaussian of sigma this share of the
    #: measured edge blur (px), in frames whose blur is at least :data:`MASK_SMOOTH_MIN_BLUR_PX`
    #: (0 = never). Smoothing below the lens's own blur takes no detail the frame still has and
    #: averages the sensor noise and JPEG blocks that make a dim, defocused ball's mask ragged
    #: (its blob then fails the shape score though the ball is whole; docs/vision.md, "Degraded
    #: frames of the planner's own layouts"). Only the mask reads the smoothed copy: the edge fit
    #: and its cut tests read the frame as it is, and the balls the first passes accepted stay.
    #: Opt-in (docs/vision.md, "Strongly blurred frames"): 1.0 with the blurred frames' ball-side
    #: floor 0.16 (``edge_fit.BLURRED_BALL_SIDE_FLOOR``) found more whole balls in degraded frames
    #: (planner-placed 12-ball tuning scenes: recall 0.22 -> 0.58, scenes trusted through the
    #: gate at frame 8 0 -> 3 of 5), but on the held-out scenes no more trusted scenes, more partly
    #: hidden balls accepted in OR frames (2 -> 4) and one trusted pose 1.02 mm off
    mask_smooth_per_blur: float = 0.0
    #: what the last searches measured of the imaging (``blur_px``: the edge blur, px;
    #: ``chroma_band_limited``: bool) and found (``centres_px``: the accepted balls' centres, px,
    #: where the next search's edge rays start, :data:`~.detection.START_AT_LAST_PX`), reused by
    #: the next search with a hint
    _imaging: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        if self.colour is not None:
            self.set_colour(self.colour)
        if edge_fit.COMPILED:
            # compile (first use after an install, ~10-20 s) or load the edge-fit kernels now,
            # not in the first frame's budget
            edge_kernels.warm_up()

    def set_colour(self, colour: BallColour) -> None:
        """Threshold ``colour`` from now on (hue band may wrap through 0 for red balls)."""
        self.colour = colour
        self.hue_lo, self.hue_hi, self.sat_min, self.val_min = (colour.hue_lo, colour.hue_hi, colour.sat_min,
                                                                 colour.val_min)

    def mask_sigma(self, blur_px: float | None) -> float:
        """The Gaussian sigma (px) of :attr:`mask_smooth_per_blur`'s look for an edge blur of
        ``blur_px`` (px; None = not known: 0)."""
        if not self.mask_smooth_per_blur or blur_px is None or not blur_px >= MASK_SMOOTH_MIN_BLUR_PX:
            return 0.0
        return float(self.mask_smooth_per_blur * blur_px)

    def band(self) -> BallColour:
        """The colour band searched (:class:`BallColour`)."""
        return BallColour(self.hue_lo, self.hue_hi, self.sat_min, self.val_min)

    def mask(self, image: np.ndarray, band: BallColour | None = None) -> np.ndarray:
        """Binary uint8 mask (0/255) of ball-coloured pixels (``band``: None = :meth:`band`)."""
        band = self.band() if band is None else band
        return cv2.morphologyEx(band.mask(image), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))

    def reads(self, hint: DetectionHint | None, shape) -> list | None:
        """What :meth:`detect` reads of a frame of ``shape`` (h, w[, 3]) with ``hint``: the
        search windows (x0, y0, x1, y1) px while the balls are tracked, None for the whole
        frame (no hint, or one that asks for the whole frame)."""
        if hint is not None and len(hint) > 0 and not hint.search_all:
            return search_windows(hint, shape)
        return None

    def detect(self, image: np.ndarray, hint: DetectionHint | None = None) -> Detection:
        """Balls in ``image`` (BGR uint8, the camera's full frame). ``hint``: the balls'
        predicted ellipses (:class:`~.detection.DetectionHint`): only windows around them are
        searched (:func:`search_windows`), or the whole frame when ``hint.search_all``; None: a
        cold full-frame search. What a search learns of the imaging (the edge blur measured
        from the balls' edges, whether the colour is band-limited) carries over to the next
        searches with a hint, so that they need no blur probe of their own (a cold search
        probes the blur first, as a single image needs)."""
        t0 = time.perf_counter()
        info: dict = {}
        windowed = hint is not None and len(hint) > 0 and not hint.search_all
        warm = hint is not None and self._imaging.get("blur_px") is not None
        frame = {"chroma_band_limited": self._imaging["chroma_band_limited"]} \
            if warm and "chroma_band_limited" in self._imaging else {}
        blur = self._imaging["blur_px"] if warm else None
        cut = []
        if windowed:
            contours, cut = self._window_contours(image, hint)
            mask = None
        else:
            contours, mask = None, self.mask(image)
        t_mask = time.perf_counter() - t0
        accepted, rejected = analyse_blobs(image, mask, self.rules, self.name, centre_method=self.centre_method,
                                           edge_blur_px=blur, contours=contours, info=info, frame=frame,
                                           hint=hint, start_px=self._imaging.get("centres_px") if warm else None)
        rejected += cut
        if self.narrow_second_pass and rejected:
            t_nar = time.perf_counter()
            accepted, rejected = self._narrowed_pass(image, accepted, rejected, hint, info, frame, warm)
            info.setdefault("stages_s", {})["narrow"] = time.perf_counter() - t_nar
        sigma = self.mask_sigma(info.get("edge_blur_px"))
        if sigma > 0 and rejected:
            t_sm = time.perf_counter()
            accepted, rejected = self._look_again(image, accepted, rejected, hint, info, frame, self.band(), sigma,
                                                  "smoothed_mask_sigma_px", sigma)
            info.setdefault("stages_s", {})["smoothed"] = time.perf_counter() - t_sm
        if self.refiner is not None and accepted:
            t_ref = time.perf_counter()
            self.refiner.refine(image, accepted)
            info.setdefault("stages_s", {})["refine"] = time.perf_counter() - t_ref
        self._imaging["centres_px"] = np.array([f.centre_px for f in accepted], float).reshape(-1, 2)
        new_blur = frame.get("blur_px_measured") or info.get("edge_blur_px")
        if new_blur is not None:
            self._imaging["blur_px"] = float(new_blur)
        if "chroma_band_limited" in frame:
            self._imaging["chroma_band_limited"] = frame["chroma_band_limited"]
        stages = {"mask": t_mask, **info.get("stages_s", {})}
        return Detection(accepted, rejected, time.perf_counter() - t0, self.name, stages_s=stages, windowed=windowed)

    def _narrowed_pass(self, image: np.ndarray, accepted: list, rejected: list, hint, info: dict, frame: dict,
                       warm: bool) -> tuple[list, list]:
        """The second look of :attr:`narrow_second_pass`: around the rejected blobs, the blobs
        of the accepted balls' own hue band (:func:`~.ball_colour.band_of_balls`; the band of an
        earlier frame of the stream when this one found too few balls) analysed as the first
        pass does (same shape score, edge fit and its checks, the blur the first pass used); a
        ball found there that no first-pass ball lies on is accepted and the rejected records
        it lies on are dropped. While tracking (a hint, also with ``search_all``) only inside the
        search windows; around every large rejected blob only in a cold search. (accepted,
        rejected)."""
        band = band_of_balls(image, accepted, self.band())
        if band is not None:
            self._imaging["ball_band"] = band
        elif warm:
            band = self._imaging.get("ball_band")
        if band is None:
            return accepted, rejected
        return self._look_again(image, accepted, rejected, hint, info, frame, band, 0.0, "narrowed_band",
                                (band.hue_lo, band.hue_hi))

    def _look_again(self, image: np.ndarray, accepted: list, rejected: list, hint, info: dict, frame: dict,
                    band: BallColour, sigma: float, feature: str, value) -> tuple[list, list]:
        """Around the rejected blobs, the blobs of the colour mask of ``band`` (the frame smoothed
        by a Gaussian of ``sigma`` px first, 0 = as it is) analysed as the first pass does (same
        shape score, edge fit and its checks, the blur the first pass used); a ball found there
        that no accepted ball lies on is accepted (its ``features[feature] = value``) and the
        rejected records it lies on are dropped. While tracking (a hint, also with
        ``search_all``) only inside the search windows; around every large rejected blob only in
        a cold search. (accepted, rejected)."""
        h, w = image.shape[:2]
        tracking = hint is not None and len(hint) > 0       # search_all too: its budget is a tracked frame's
        lo = float(self.rules.radius_range_px[0])
        big = sorted((r for r in rejected if r.area_px >= np.pi * lo * lo), key=lambda r: -r.area_px)[:NARROW_MAX_BLOBS]
        boxes = []
        for r in big:
            half = np.asarray(r.axes_px, float)
            g = NARROW_BOX_MARGIN_PX + float(np.max(half))
            cx, cy = float(r.centre_px[0]), float(r.centre_px[1])
            if np.isfinite(cx) and np.isfinite(cy) and np.isfinite(g):
                boxes.append((max(int(cx - g), 0), max(int(cy - g), 0), min(int(np.ceil(cx + g)) + 1, w),
                              min(int(np.ceil(cy + g)) + 1, h)))
        if tracking:
            # only inside the search windows (a drape filling the view would cost a full-frame
            # mask each frame)
            windows = search_windows(hint, (h, w))
            boxes = [(max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3]))
                     for a in windows for b in boxes if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]]
        boxes = [b for b in _merged(boxes) if b[2] - b[0] >= 3 and b[3] - b[1] >= 3]
        if not boxes:
            return accepted, rejected
        contours, _cut_boxes, _cut = self._contours_in(image, boxes, band, sigma)
        # the balls the first pass accepted are found again here: not fitted a second time
        done = np.array([f.centre_px for f in accepted], float).reshape(-1, 2)
        tol = np.array([max(3.0, 0.5 * float(min(f.axes_px))) for f in accepted], float)
        if len(done):
            rects = np.array([cv2.boundingRect(c) for c in contours], float).reshape(-1, 4)
            mid = rects[:, :2] + rects[:, 2:] / 2.0
            near = (np.hypot(mid[:, None, 0] - done[None, :, 0], mid[:, None, 1] - done[None, :, 1]) <= tol).any(axis=1)
            contours = [c for c, n in zip(contours, near) if not n]
        if not contours:
            return accepted, rejected
        rules = self.rules if self.narrow_min_score is None else replace(self.rules, min_score=self.narrow_min_score)
        more, _ = analyse_blobs(image, None, rules, self.name, centre_method=self.centre_method,
                                edge_blur_px=info.get("edge_blur_px"), contours=contours,
                                frame=dict(frame), hint=hint,    # a copy: the first pass's blur stands
                                size_peers=[f.axes_px[1] for f in accepted])

        def on(f, others) -> bool:
            return any(np.hypot(*(np.asarray(f.centre_px) - o.centre_px)) <= max(2.0, 0.5 * min(o.axes_px))
                       for o in others)

        new = [f for f in more if not on(f, accepted)]
        if not new:
            return accepted, rejected
        for f in new:
            f.features[feature] = value
        kept = [r for r in rejected if not any(np.hypot(*(np.asarray(r.centre_px) - f.centre_px)) <= max(2.0, min(f.axes_px))
                                               for f in new)]
        out = sorted(accepted + new, key=lambda c: (c.centre_px[1], c.centre_px[0]))
        return out, kept

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

    def _window_masks(self, image: np.ndarray, boxes: list, band: BallColour | None = None) -> list:
        """:meth:`mask` of each window (x0, y0, x1, y1 px) of ``image``, as if each were masked on
        its own (the opening's border left as OpenCV leaves an image's), in one colour conversion,
        one threshold, one erosion and one dilation of the windows stacked into a mosaic (one
        call per window cost ~50-100 us of overhead each, 9 windows a frame; issue 29). Between
        and beside the windows lies padding that counts as set for the erosion and as unset for
        the dilation: OpenCV's default border for each (a window's pixels never see another's)."""
        w_max = max(x1 - x0 for x0, _y0, x1, _y1 in boxes)
        rows = sum(y1 - y0 + 1 for _x0, y0, _x1, y1 in boxes) + 1
        mosaic = np.zeros((rows, w_max + 2, 3), np.uint8)
        pad = np.ones((rows, w_max + 2), bool)
        at, places = 1, []
        for x0, y0, x1, y1 in boxes:
            h_, w_ = y1 - y0, x1 - x0
            mosaic[at:at + h_, 1:1 + w_] = image[y0:y1, x0:x1]
            pad[at:at + h_, 1:1 + w_] = False
            places.append((at, h_, w_))
            at += h_ + 1
        band = (self.band() if band is None else band).mask(mosaic)
        band[pad] = 255
        kernel = np.ones((3, 3), np.uint8)
        band = cv2.erode(band, kernel)
        band[pad] = 0
        band = cv2.dilate(band, kernel)
        return [band[a:a + h_, 1:1 + w_] for a, h_, w_ in places]

    def _contours_in(self, image: np.ndarray, boxes: list, band: BallColour | None = None,
                     sigma: float = 0.0) -> tuple[list, set, list]:
        """Blobs of the colour mask (``band``: None = :meth:`band`; ``sigma`` px > 0: of the
        frame smoothed by that Gaussian first) inside ``boxes`` (x0, y0, x1, y1 px): (whole
        contours, indices of the boxes a blob leaves through an edge that is not the image's,
        those blobs' contours)."""
        h, w = image.shape[:2]
        if not boxes:
            return [], set(), []
        b = np.array(boxes)
        X0, Y0, X1, Y1 = int(b[:, 0].min()), int(b[:, 1].min()), int(b[:, 2].max()), int(b[:, 3].max())
        if sigma > 0:
            image = _smoothed_part(image, (X0, Y0, X1, Y1), sigma)
        mask = np.zeros((Y1 - Y0, X1 - X0), np.uint8)
        inner = np.zeros_like(mask)          # window pixels that are not on a window's inner edge
        inside = np.zeros_like(mask)         # window pixels
        area = 0
        for x0, y0, x1, y1 in boxes:
            inside[y0 - Y0:y1 - Y0, x0 - X0:x1 - X0] = 255
            ix0, iy0 = x0 + (x0 > 0), y0 + (y0 > 0)
            ix1, iy1 = x1 - (x1 < w), y1 - (y1 < h)
            inner[iy0 - Y0:iy1 - Y0, ix0 - X0:ix1 - X0] = 1
            area += (x1 - x0) * (y1 - y0)
        if mask.size <= WINDOW_BBOX_FACTOR * area + WINDOW_BBOX_PX * len(boxes):
            # one colour conversion of the windows' bounding box costs less than one per window
            cv2.bitwise_and(self.mask(image[Y0:Y1, X0:X1], band), inside, dst=mask)
        else:
            for (x0, y0, x1, y1), sub in zip(boxes, self._window_masks(image, boxes, band)):
                np.maximum(mask[y0 - Y0:y1 - Y0, x0 - X0:x1 - X0], sub, out=mask[y0 - Y0:y1 - Y0, x0 - X0:x1 - X0])
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


#: :attr:`ClassicalDetector.mask_smooth_per_blur`'s look happens only in frames whose measured
#: edge blur (px) is at least this (the edge fit's own line between a sharp frame and a blurred
#: one, ``edge_fit.SHARP_BLUR_PX``)
MASK_SMOOTH_MIN_BLUR_PX = edge_fit.SHARP_BLUR_PX[1]


def _smoothed_part(image: np.ndarray, box, sigma: float) -> np.ndarray:
    """A copy of ``image`` whose ``box`` (x0, y0, x1, y1 px) is smoothed by a Gaussian of
    ``sigma`` px as the whole frame would be there (read with a 3-sigma margin of the frame
    around the box); the rest of the copy is the frame as it is."""
    h, w = image.shape[:2]
    m = int(np.ceil(3.0 * sigma)) + 1
    x0, y0, x1, y1 = box
    xa, ya, xb, yb = max(x0 - m, 0), max(y0 - m, 0), min(x1 + m, w), min(y1 + m, h)
    out = image.copy()
    out[y0:y1, x0:x1] = cv2.GaussianBlur(image[ya:yb, xa:xb], (0, 0), sigma)[y0 - ya:y1 - ya, x0 - xa:x1 - xa]
    return out


#: :attr:`ClassicalDetector.narrow_second_pass` looks again in boxes around each rejected blob
#: reaching this far (px) beyond its half size, for the rejected blobs at least as large as the
#: smallest plausible ball, the largest this many
NARROW_BOX_MARGIN_PX = 6.0
NARROW_MAX_BLOBS = 24


#: a search window reaches beyond a ball's predicted ellipse by this much (px) + this share of
#: its semi-major axis, + per frame of the hint's age beyond the first: the head's motion between
#: frames (up to ~50 mm/s: ~3.5 px per frame at 0.5 m with f = 1100 px) and the prediction's
#: error. A ball that moved on the skin by more is found by the next full-frame search.
WINDOW_MARGIN_PX = 8.0
WINDOW_MARGIN_PER_RADIUS = 0.5
WINDOW_MARGIN_PER_AGE_PX = 6.0
#: the windows' colour mask is made from their bounding box in one go (then cut to the windows)
#: when that box is smaller than this many times their area + this many px per window (one
#: colour conversion per window costs ~40-80 us of overhead, ~2-5 ns per pixel)
WINDOW_BBOX_FACTOR = 3.0
WINDOW_BBOX_PX = 10000


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
