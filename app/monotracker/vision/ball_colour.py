"""The balls' colour as a setting: an HSV band, learned from one click on a ball.

:class:`BallColour` is the band the classical detector thresholds (OpenCV's HSV scale: hue
0-180, saturation and value 0-255). Green (hue 35-90, saturation >= 90, value >= 35) is the
default. ``hue_lo > hue_hi`` means a band that wraps through 0 (red balls).

:func:`learn_ball_colour` takes the image and the clicked pixel and either returns the band of
the ball under the click or raises :class:`~monotracker.errors.InputError` with a one-line
reason the user can act on: the click is on something grey (skin, steel, a glove), on a region
that is not round and ball-sized (a drape, a strip), or too close to the image border.

How (choices written down): the click's colour is the median of a 5x5 window; pixels of similar
hue (+-14) and saturation (>= half of the click's) connected to the click form the region
(bounded to a 161x161 window: a ball is never that big). The region must be round (axis ratio
>= 0.6), filled (area / fitted ellipse area >= 0.7) and between 3 and 60 px in radius. The band
is the 2nd-98th percentile of the region's hue widened by 6, value >= 0.4 x its 10th percentile
(>= 20), saturation >= 0.5 x its 10th percentile (>= 40), raised in steps up to 0.9 x until the
ball thresholded with the band is a blob of its own (skin shares an orange ball's hue): shading
and a dim side keep passing, drapes and skin of a neighbouring colour do not.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from monotracker.errors import InputError

#: keys of the colour in a calibration file (JSON object ``ball_colour`` / YAML ``ball_colour_*``)
FIELDS = ("hue_lo", "hue_hi", "sat_min", "val_min")


@dataclass(frozen=True)
class BallColour:
    """HSV band of the balls (OpenCV scale). ``hue_lo > hue_hi`` wraps through hue 0."""

    hue_lo: int = 35
    hue_hi: int = 90
    sat_min: int = 90
    val_min: int = 35

    def __post_init__(self):
        problem = validate_colour(self.hue_lo, self.hue_hi, self.sat_min, self.val_min)
        if problem:
            raise InputError(f"invalid ball colour: {problem}")

    def mask(self, image_bgr: np.ndarray) -> np.ndarray:
        """uint8 0/255 mask of the pixels inside the band (no morphology)."""
        return self.mask_hsv(cv2.cvtColor(image_bgr, cv2.COLOR_BGR2HSV))

    def mask_hsv(self, hsv: np.ndarray) -> np.ndarray:
        """:meth:`mask` of an image already converted to HSV (OpenCV's scale)."""
        if self.hue_lo <= self.hue_hi:
            return cv2.inRange(hsv, (self.hue_lo, self.sat_min, self.val_min), (self.hue_hi, 255, 255))
        a = cv2.inRange(hsv, (self.hue_lo, self.sat_min, self.val_min), (180, 255, 255))
        b = cv2.inRange(hsv, (0, self.sat_min, self.val_min), (self.hue_hi, 255, 255))
        return cv2.bitwise_or(a, b)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data, where: str = "ball colour") -> "BallColour":
        """From a mapping with :data:`FIELDS`; :class:`InputError` naming ``where`` otherwise."""
        if not isinstance(data, dict):
            raise InputError(f"{where}: expected hue_lo, hue_hi, sat_min, val_min")
        missing = [k for k in FIELDS if k not in data]
        if missing:
            raise InputError(f"{where} lacks {', '.join(missing)}")
        try:
            vals = {k: int(round(float(data[k]))) for k in FIELDS}
        except (TypeError, ValueError):
            raise InputError(f"{where}: hue_lo, hue_hi, sat_min, val_min must be numbers") from None
        problem = validate_colour(**vals)
        if problem:
            raise InputError(f"{where}: {problem}")
        return cls(**vals)


def validate_colour(hue_lo, hue_hi, sat_min, val_min) -> str:
    """'' when the band is usable, else a one-line reason."""
    if not (0 <= hue_lo <= 180 and 0 <= hue_hi <= 180):
        return f"hue must lie in 0-180 (OpenCV scale), got {hue_lo}-{hue_hi}"
    if not (0 <= sat_min <= 255 and 0 <= val_min <= 255):
        return f"saturation/value minima must lie in 0-255, got {sat_min}/{val_min}"
    if sat_min < 30:
        return f"saturation minimum {sat_min} < 30 would accept skin, steel and gloves"
    width = (hue_hi - hue_lo) % 180
    if width > 70:
        return f"hue band {hue_lo}-{hue_hi} is wider than 70 (it would take in drapes and skin)"
    return ""


def learn_ball_colour(image_bgr: np.ndarray, xy_px) -> BallColour:
    """The colour band of the ball under pixel ``xy_px`` = (x, y) of ``image_bgr`` (BGR uint8).
    Raises :class:`InputError` with the reason when the click is not on a ball-like region."""
    img = np.asarray(image_bgr)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise InputError("ball colour: need a BGR 8-bit colour image")
    h, w = img.shape[:2]
    try:
        x, y = int(round(float(xy_px[0]))), int(round(float(xy_px[1])))
    except (TypeError, ValueError, IndexError):
        raise InputError("ball colour: the click must be two pixel coordinates (x, y)") from None
    if not (0 <= x < w and 0 <= y < h):
        raise InputError(f"ball colour: click ({x}, {y}) lies outside the {w}x{h} image")
    half = 80
    x0, y0, x1, y1 = max(x - half, 0), max(y - half, 0), min(x + half + 1, w), min(y + half + 1, h)
    hsv = cv2.cvtColor(img[y0:y1, x0:x1], cv2.COLOR_BGR2HSV)
    cx, cy = x - x0, y - y0
    win = hsv[max(cy - 2, 0):cy + 3, max(cx - 2, 0):cx + 3].reshape(-1, 3).astype(float)
    hue0 = _circular_median(win[:, 0])
    sat0, val0 = float(np.median(win[:, 1])), float(np.median(win[:, 2]))
    if sat0 < 60 or val0 < 30:
        raise InputError("ball colour: the click is not on a coloured ball (grey, dark or white there: "
                         "skin, steel, glove or a highlight?); click the middle of a ball")
    dh = np.abs(((hsv[..., 0].astype(int) - int(round(hue0))) + 90) % 180 - 90)
    similar = ((dh <= 14) & (hsv[..., 1] >= 0.5 * sat0) & (hsv[..., 2] >= 0.3 * val0)).astype(np.uint8)
    # close small holes (a specular highlight) before taking the region connected to the click
    similar = cv2.morphologyEx(similar, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(similar, connectivity=8)
    lab = labels[cy, cx]
    if lab == 0:
        raise InputError("ball colour: no uniform colour under the click; click the middle of a ball")
    bx, by, bw, bh, area = stats[lab]
    if bx == 0 or by == 0 or bx + bw >= similar.shape[1] or by + bh >= similar.shape[0]:
        raise InputError("ball colour: the clicked colour region is larger than a ball or cut by the "
                         "image border (a drape?); click a ball fully in view")
    region = (labels == lab).astype(np.uint8)
    cnts, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cnt = max(cnts, key=cv2.contourArea)
    if len(cnt) < 5:
        raise InputError("ball colour: the clicked region is too small for a ball")
    (_, _), (d1, d2), _ = cv2.fitEllipse(cnt)
    a, b = max(d1, d2) / 2, min(d1, d2) / 2
    filled = cv2.morphologyEx(region, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    fill = float(filled.sum()) / (np.pi * a * b + 1e-9)
    if not (3.0 <= b and a <= 60.0):
        raise InputError(f"ball colour: the clicked region ({2 * a:.0f} px across) is not ball-sized")
    if b / a < 0.6 or fill < 0.7:
        raise InputError("ball colour: the clicked region is not round (a strip, a drape fold or a cut "
                         "ball?); click a ball fully in view")
    px = hsv[region > 0].astype(float)
    hue_rel = ((px[:, 0] - hue0 + 90) % 180) - 90
    lo, hi = np.percentile(hue_rel, [2, 98])
    hue_lo = int(np.floor(hue0 + lo - 6)) % 180
    hue_hi = int(np.ceil(hue0 + hi + 6)) % 180
    val_min = int(max(20, 0.4 * np.percentile(px[:, 2], 10)))
    sat10 = float(np.percentile(px[:, 1], 10))
    # the lowest saturation floor at which the ball stays a blob of its own (skin can share an
    # orange ball's hue, a drape a green one's: saturation then tells them apart)
    for f in (0.5, 0.6, 0.7, 0.8, 0.9):
        colour = BallColour(hue_lo, hue_hi, int(max(40, f * sat10)), val_min)
        if _separate(colour, img[y0:y1, x0:x1], (cx, cy), area, region):
            return colour
    raise InputError("ball colour: the ball's colour also covers its surroundings (skin or drape of the "
                     "same hue and saturation); use balls of another colour")


#: :func:`band_of_balls`: the core of each found ball sampled (this share of its minor
#: semi-axis), the hue band is the 10th-90th percentile of those pixels widened by this much
#: (OpenCV hue units), and at least this many balls must speak for it
CORE_SHARE = 0.6
HUE_PERCENTILE = 10
HUE_MARGIN = 8
MIN_BALLS = 1


def band_of_balls(image_bgr: np.ndarray, balls: list, within: BallColour) -> BallColour | None:
    """The hue band of the balls a detector found in ``image_bgr`` (``balls``: objects with
    ``centre_px`` and ``axes_px`` px), inside the band ``within`` it searched with: the
    10th-90th percentile (:data:`HUE_PERCENTILE`) of the hue of their cores' in-band pixels
    (:data:`CORE_SHARE`; a dark limb's and a highlight's hue stray) widened by
    :data:`HUE_MARGIN`, intersected with ``within`` (same saturation and value floors). None when
    fewer than :data:`MIN_BALLS` balls, a band that wraps through hue 0, or no narrower band.
    What it is for: the balls of one kit share one dye, while a drape of a neighbouring hue (a
    teal one beside green balls) passes the wide default band and merges with a ball touching
    it into one blob that is no ball; thresholded with the balls' own band they part."""
    if len(balls) < MIN_BALLS or within.hue_lo > within.hue_hi:
        return None
    h, w = image_bgr.shape[:2]
    hues = []
    for b in balls:
        cx, cy = float(b.centre_px[0]), float(b.centre_px[1])
        r = CORE_SHARE * float(min(b.axes_px))
        x0, y0 = max(int(np.floor(cx - r)), 0), max(int(np.floor(cy - r)), 0)
        x1, y1 = min(int(np.ceil(cx + r)) + 1, w), min(int(np.ceil(cy + r)) + 1, h)
        if r < 1.0 or x1 <= x0 or y1 <= y0:
            continue
        crop = np.ascontiguousarray(image_bgr[y0:y1, x0:x1])
        hsv = cv2.cvtColor(crop, cv2.COLOR_BGR2HSV)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        core = ((xx - cx) ** 2 + (yy - cy) ** 2 <= r * r) & (within.mask_hsv(hsv) > 0)
        if core.any():
            hues.append(hsv[..., 0][core].astype(float))
    if len(hues) < MIN_BALLS:
        return None
    hue = np.concatenate(hues)
    lo, hi = np.percentile(hue, [HUE_PERCENTILE, 100 - HUE_PERCENTILE])
    lo, hi = max(int(np.floor(lo)) - HUE_MARGIN, within.hue_lo), min(int(np.ceil(hi)) + HUE_MARGIN, within.hue_hi)
    if hi < lo or (lo, hi) == (within.hue_lo, within.hue_hi):
        return None
    return BallColour(lo, hi, within.sat_min, within.val_min)


def _separate(colour: BallColour, roi: np.ndarray, click, area: float, region: np.ndarray) -> bool:
    """True when, thresholded with ``colour``, the blob under ``click`` is about the clicked
    region's size (<= 2x its ``area`` px) and not connected to the window's border, and the
    ring 4-12 px around the ball ``region`` is < 1 % in the band."""
    m = cv2.morphologyEx(colour.mask(roi), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    around = (cv2.dilate(region, np.ones((25, 25), np.uint8)) > 0) & (cv2.dilate(region, np.ones((9, 9), np.uint8)) == 0)
    if np.count_nonzero(m[around]) > 0.01 * np.count_nonzero(around):
        return False
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    lab = labels[click[1], click[0]]
    if lab == 0:
        return True          # the click itself is a highlight: judge by the ball's blob instead
    bx, by, bw, bh, a = stats[lab]
    inside = bx > 0 and by > 0 and bx + bw < m.shape[1] and by + bh < m.shape[0]
    return bool(inside and a <= 2.0 * area)


def _circular_median(h: np.ndarray) -> float:
    """Median of hues on OpenCV's circular 0-180 scale."""
    ref = h[len(h) // 2]
    rel = ((h - ref + 90) % 180) - 90
    return float((ref + np.median(rel)) % 180)
