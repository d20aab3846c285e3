"""Image fiducials and the shared blob analysis of both detectors.

A detector returns a :class:`Detection`: the accepted :class:`ImageFiducial` list (centre px
in the distorted image, semi-axes px, angle deg, score in [0, 1]) and the rejected candidates
with the reason. ``centres`` ((n, 2) float64 px) is what goes to the registration, together
with the sphere radius so that the ellipse-centre bias is corrected there.

Sub-pixel centre, ``centre_method="edge"`` (the default): the ball's edge is unmixed from its
local background ray by ray in linear radiance and an ellipse is fitted to it
(:mod:`monotracker.vision.edge_fit`); it holds under lens blur, gloss, shading and any
background colour. A ball whose edge fit is refused (cut by an occluder, no contrast) is
rejected with that reason.

``centre_method="chroma"`` (the previous method, kept as the benchmark's baseline;
:func:`refine_blob`): the centroid of a soft mask. The weight of a pixel is
its green chromaticity ``(G - R) / (B + G + R)`` mapped linearly from the local background level
(median of a ring around the blob) to the blob's interior level (median of its eroded core)
and clipped to [0, 1]. Chromaticity does not depend on shading, so the lit and the shadowed
side of a ball weigh the same, and anti-aliased edge pixels get fractional weight: the
centroid is that of the silhouette, i.e. the ellipse centre (an ellipse's area centroid is its
centre), to ~0.1 px on sharp frames; under lens blur it is pulled towards backgrounds of
positive green chromaticity (blue drape: ~1 px).

Shape score (:func:`score_blob`): product of four factors, each 1 for a clean sphere image:
* boundary fit: RMS radial deviation (px) of the blob contour from the ellipse fitted by
  ``cv2.fitEllipse`` after removing the mean offset, ``exp(-(rms / scale)^2)`` (scale 0.6 px, in
  proportion to the ball's size above 8 px radius: :data:`FIT_RMS_SCALE_PER_RADIUS`); a ball cut by a
  finger or an instrument has a straight chord and scores low;
* roundness: spheres within the field of view make ellipses with axis ratio >= 0.8;
* fill: blob area / fitted ellipse area close to 1 (a cut ball or an irregular blob is not);
* size: the minor semi-axis must lie in the range a ball of ``radius_mm`` makes between
  ``min_distance_mm`` and ``max_distance_mm``, and near the median of the other candidates
  (all balls sit at about the same depth); outliers beyond +-25 % are down-weighted.
Candidates scoring below ``min_score`` are rejected with their reason.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from . import edge_fit, edge_kernels, skin_band
from .ball_gloss import highlight_ratio
from .edge_fit import fit_ball_edges, measure_edge_blur
from .shading_shift import shaded_centre
from .sphere_outline import expected_shapes

#: sub-pixel centre methods of :func:`analyse_blobs`
CENTRE_METHODS = ("edge", "chroma")


@dataclass
class ImageFiducial:
    """One detected ball: ``centre_px`` (2,), ``axes_px`` (semi-major, semi-minor), ``angle_deg``
    of the major axis (OpenCV's fitEllipse convention), ``score`` in [0, 1], ``area_px``,
    ``reason`` (why it was rejected; '' if accepted), ``features`` (the score's factors)."""

    centre_px: np.ndarray
    axes_px: tuple
    angle_deg: float
    score: float
    area_px: float
    reason: str = ""
    features: dict = field(default_factory=dict)


@dataclass
class Detection:
    """Detector output for one frame; ``time_s`` is the detector's wall time."""

    fiducials: list
    rejected: list
    time_s: float = 0.0
    detector: str = ""
    #: '' or why this detector declines the frame (one line; e.g. the learned detector seeing
    #: rings or nothing); its ``fiducials`` are then empty
    refusal: str = ""
    #: wall time (s) per stage of the detector (e.g. mask, contours, shape, outline, blur,
    #: edge_fit; what a detector reports), for profiles and the pose-rate benchmark
    stages_s: dict = field(default_factory=dict)
    #: True when the detector searched windows around a hint only, False for a full-frame search
    windowed: bool = False

    @property
    def centres(self) -> np.ndarray:
        return np.array([f.centre_px for f in self.fiducials], float).reshape(-1, 2)

    @property
    def scores(self) -> np.ndarray:
        return np.array([f.score for f in self.fiducials], float)


@dataclass(frozen=True)
class DetectionHint:
    """Where the balls should be in the next frame: their image ellipses predicted from the last
    trusted pose (:meth:`from_pose`). A detector given one (``detect(image, hint)``) may search
    windows around these ellipses only; ``hint=None`` means a full-frame search. A hint is a
    prediction, not a measurement: a detector must still find and fit every ball in the image,
    and report nothing where it finds none.

    Attributes:
        centres_px: (n, 2) float, distorted px: predicted ellipse centres (the image of each
            sphere's silhouette, not the projected sphere centre).
        axes_px: (n, 2) float, px: predicted semi-axes (semi-major, semi-minor).
        angles_deg: (n,) float, deg: major axis direction, from +x towards +y (image axes).
        fiducial_indices: (n,) int: which fiducial (index into the pose tracker's CT array; the
            tracker's watched extra balls follow after its registration fiducials) each row is.
        frame_index: index of the frame whose trusted pose made the prediction.
        age_frames: frames between that pose and the frame to search (>= 1): the balls may have
            moved further the older the pose, so a detector widens its windows with it.
        search_all: the whole frame is to be searched all the same (see the field).
    """

    centres_px: np.ndarray
    axes_px: np.ndarray
    angles_deg: np.ndarray
    fiducial_indices: np.ndarray
    frame_index: int = -1
    age_frames: int = 1
    #: search the whole frame all the same (new balls, strays, a drape of the balls' colour),
    #: the predictions still valid: what the imaging of the last frames taught the detector
    #: (the edge blur, the colour's bandwidth) still holds
    search_all: bool = False

    def __post_init__(self):
        c = np.asarray(self.centres_px, float).reshape(-1, 2)
        n = len(c)
        object.__setattr__(self, "centres_px", c)
        object.__setattr__(self, "axes_px", np.asarray(self.axes_px, float).reshape(n, 2))
        object.__setattr__(self, "angles_deg", np.asarray(self.angles_deg, float).reshape(n))
        object.__setattr__(self, "fiducial_indices", np.asarray(self.fiducial_indices, int).reshape(n))

    def __len__(self) -> int:
        return len(self.centres_px)

    @classmethod
    def from_pose(cls, camera, T_cam_ct: np.ndarray, centres_ct, radius_mm: float, frame_index: int = -1,
                  age_frames: int = 1, fiducial_indices=None, search_all: bool = False,
                  ellipses=None) -> "DetectionHint":
        """The image ellipses of spheres of ``radius_mm`` (mm) at ``centres_ct`` ((n, 3) CT mm)
        under the pose ``T_cam_ct`` (4x4, CT mm -> camera mm) seen by ``camera`` (a
        :class:`~.camera_model.CameraModel`, lens distortion included). Balls behind the camera,
        or where the distortion model does not invert, are left out. ``ellipses``: what computes
        them (:func:`~.sphere_outline.sphere_ellipses` when None; a stream of frames passes a
        :class:`~.sphere_outline.SphereEllipseCache`, which reuses them between frames)."""
        from .sphere_outline import sphere_ellipses

        X = np.asarray(centres_ct, float).reshape(-1, 3)
        idx = np.arange(len(X)) if fiducial_indices is None else np.asarray(fiducial_indices, int).reshape(-1)
        Xc = X @ np.asarray(T_cam_ct, float)[:3, :3].T + np.asarray(T_cam_ct, float)[:3, 3]
        cen, axes, ang, ok = (ellipses or sphere_ellipses)(camera, Xc, radius_mm)
        return cls(cen[ok], axes[ok], ang[ok], idx[ok], int(frame_index), max(int(age_frames), 1), bool(search_all))


def oversized_colour_share(det: "Detection", rules: "BlobRules", image_shape) -> float:
    """Share (0-1) of the image covered by ball-coloured blobs larger than any ball can image
    (area over that of a disc of 1.5 x the largest ball radius, ``rules``): a drape, a cover or a
    wall of the balls' hue. Balls next to such an area merge with it in the mask (they are lost,
    or analysed as holes in it), so a share over a few percent means the colour band is not
    selective here (learn the ball colour from a click)."""
    big = np.pi * (1.5 * rules.radius_range_px[1]) ** 2
    area = sum(float(r.area_px) for r in det.rejected if float(r.area_px) > big)
    return area / float(image_shape[0] * image_shape[1])


@dataclass
class BlobRules:
    """Plausibility limits of a ball's image. Units: mm, px."""

    radius_mm: float = 4.0
    focal_px: float = 1100.0
    min_distance_mm: float = 250.0
    max_distance_mm: float = 1000.0
    min_score: float = 0.5
    min_area_px: float = 12.0
    #: the calibrated camera (:class:`~.camera_model.CameraModel`) of the images, or None: with
    #: it each ball's edge is fitted with the outline a whole sphere has at its place in the
    #: image (:mod:`.sphere_outline`), which keeps a ball cut by an occluder from a biased centre.
    #: :class:`~.pose_tracker.PoseTracker` sets (replaces) it on its detector's rules: do not
    #: share one BlobRules between detectors of different cameras. Images of another size than
    #: the camera's are refused (ValueError)
    camera: object = None
    #: move an edge-fitted shaded ball's centre back towards the sphere's
    #: (:mod:`.shading_shift`: the push of an unlit limb read with its contact shadow)
    shading_shift: bool = False
    #: the edge fit leaves out a shadowed ray inside the fitted outline beyond this depth (px;
    #: None: :data:`.edge_fit.SHADOW_IN_PX`, the default; inf: only rays outside it, the rule
    #: before 2026-12-01, ``benchmarks/camera_pbr.py``'s ``outside-only``)
    shadow_in_px: float | None = None
    #: ... and judges a ray's background as a shadow's against the background this share of the
    #: ball's radius further out (at least :data:`.edge_fit.SHADOW_FAR_PX`; None:
    #: :data:`.edge_fit.SHADOW_FAR_PER_RADIUS`, the default 0: 3 px whatever the ball's size;
    #: 0.5 is ``benchmarks/camera_pbr.py``'s opt-in ``long-shadow``)
    shadow_far_per_radius: float | None = None
    #: a blob whose shape scores too low is scored again with its thin parts cut off
    #: (:func:`trim_tail`; opt-in, ``benchmarks/camera_pbr.py``'s ``trim``: a mixed result,
    #: docs/vision.md "Ragged colour blobs scored again trimmed"); False: refused as it is
    trim_tails: bool = False
    #: a ball whose skin band ratio (:mod:`.skin_band`: the skin just beyond its unlit limb against
    #: the lit side's) is under this shows a band of contact shadow (``features["skin_band"]``,
    #: which the pose tracker's shading check counts); 0: not read (``benchmarks/camera_pbr.py``'s
    #: ``no-band``, the detector before 2026-12-03)
    skin_band_ratio: float = skin_band.BAND_RATIO

    @property
    def radius_range_px(self) -> tuple[float, float]:
        return (self.focal_px * self.radius_mm / self.max_distance_mm,
                self.focal_px * self.radius_mm / self.min_distance_mm)


def green_chroma(bgr: np.ndarray) -> np.ndarray:
    """(G - R) / (B + G + R) per pixel, float32 in [-1, 1]."""
    f = bgr.astype(np.float32)
    return (f[..., 1] - f[..., 2]) / (f.sum(axis=2) + 1.0)


def refine_blob(image: np.ndarray, contour: np.ndarray, pad: int = 3) -> tuple[np.ndarray, float, np.ndarray] | None:
    """Sub-pixel centre of the blob outlined by ``contour``: (centre (2,), soft area px,
    2x2 covariance of the soft mask). None when the blob is degenerate."""
    h, w = image.shape[:2]
    x, y, bw, bh = cv2.boundingRect(contour)
    x0, y0 = max(x - pad, 0), max(y - pad, 0)
    x1, y1 = min(x + bw + pad, w), min(y + bh + pad, h)
    roi = image[y0:y1, x0:x1]
    chroma = green_chroma(roi)
    inside = np.zeros(roi.shape[:2], np.uint8)
    cv2.drawContours(inside, [contour - [x0, y0]], -1, 255, -1)
    grown = cv2.dilate(inside, np.ones((3, 3), np.uint8), iterations=2)
    core = cv2.erode(inside, np.ones((3, 3), np.uint8), iterations=1)
    ring = (grown == 0)
    if not ring.any():
        ring = inside == 0
    fg = float(np.median(chroma[core > 0])) if core.any() else float(np.median(chroma[inside > 0]))
    bg = float(np.median(chroma[ring])) if ring.any() else 0.0
    if fg - bg < 0.05:
        return None
    wgt = np.clip((chroma - bg) / (fg - bg), 0.0, 1.0) * (grown > 0)
    m = cv2.moments(wgt.astype(np.float32))
    if m["m00"] <= 1e-6:
        return None
    cx, cy = m["m10"] / m["m00"], m["m01"] / m["m00"]
    cov = np.array([[m["mu20"], m["mu11"]], [m["mu11"], m["mu02"]]]) / m["m00"]
    return np.array([cx + x0, cy + y0]), float(m["m00"]), cov


#: the boundary-fit factor's scale: ``exp(-(rms / scale)^2)`` with scale = max(this px, the
#: next x the blob's minor semi-axis px). A ball's pixel outline strays from an ellipse by a
#: share of its size (shading dents its colour mask, a highlight bites into it): on the
#: physically rendered tuning frames whole balls that reach the edge fit stray 3-4.5 % of their
#: radius (median), those refused as "not elliptic" 4.3-6.6 %, at 6-14 px radius alike. With a
#: fixed 0.6 px a 13 px ball straying 0.57 px (4.3 %) was refused: whole-ball recall 0.23-0.31 in
#: clean and degraded scenes with the camera placed as the layout planner advises (300-450 mm,
#: ``scripts/render_planned.py``). 0.6 px up to an 8 px radius (where the rule was set), in
#: proportion above. A ball cut by an occluder is refused further on by the edge fit's cut test,
#: which knows the outline's shape
FIT_RMS_SCALE_PX = 0.6
FIT_RMS_SCALE_PER_RADIUS = 0.075


def score_blob(contour: np.ndarray, area: float, rules: BlobRules) -> tuple[float, dict, tuple]:
    """Shape score of one blob (see the module docstring): (score, factors, fitted ellipse)."""
    if len(contour) < 5:
        return 0.0, {"why": "too few contour points"}, None
    raw = cv2.fitEllipse(contour)
    (ex, ey), (d1, d2), ang = raw
    a, b = max(d1, d2) / 2, min(d1, d2) / 2
    if b <= 0.5:
        return 0.0, {"why": "degenerate ellipse"}, None
    # radial deviation of the contour from the fitted ellipse (RMS about its mean, px)
    rms = float(edge_kernels.contour_fit_rms(contour.reshape(-1, 1, 2), float(ex), float(ey), float(d1), float(d2),
                                             float(ang)))
    ratio = b / a
    fill = area / (np.pi * a * b)
    lo, hi = rules.radius_range_px
    f_fit = math.exp(-(rms / max(FIT_RMS_SCALE_PX, FIT_RMS_SCALE_PER_RADIUS * b)) ** 2)
    f_round = min(max((ratio - 0.6) / 0.2, 0.0), 1.0)
    f_fill = math.exp(-((fill - 1.0) / 0.12) ** 2)
    f_range = 1.0 if lo * 0.8 <= b + 0.5 <= hi * 1.2 else 0.0
    factors = {"fit_rms_px": rms, "axis_ratio": ratio, "fill": fill, "f_fit": f_fit, "f_round": f_round,
               "f_fill": f_fill, "f_range": f_range, "contour_ellipse": raw}
    return f_fit * f_round * f_fill * f_range, factors, ((ex, ey), (a, b), ang)


#: a blob whose shape scores too low is looked at again with its thin parts cut off
#: (:func:`trim_tail`, ``BlobRules.trim_tails``, opt-in): a morphological opening with a disc of
#: this share of the blob's fitted minor semi-axis (px). Why it was tried: whole balls of the
#: rendered tuning sets refused before their edge was ever fitted ("score: boundary not
#: elliptic": 12 % of the whole balls in clean frames, 19 % in degraded ones), their colour masks
#: frayed by a contact shadow's fringe, a shadowed limb or a highlight's bite. Opening with a disc
#: of 0.4 x the minor semi-axis keeps a disc of the ball's size whole and cuts off parts narrower
#: than 0.8 x it. Not the default (docs/vision.md, "Ragged colour blobs scored again trimmed"):
#: what it cuts off is mostly a few px of fray, not a tail, so it acts much like a lower blob-score
#: floor (tried twice before, not kept), and on independent renders of balls cut by an occluder
#: (blurred, noisy, JPEG 70) it lets 20 of 150 through instead of 13, 12 instead of 7 more than
#: 0.5 px off.
TRIM_TAIL_SHARE = 0.4
#: ... kept only when the part left is still the ball: its minor semi-axis at least this share
#: of the untrimmed blob's (a tail does not change the ball's width; a blob trimmed down to a
#: fragment is no ball) ...
TRIM_KEEP_MINOR = 0.85
#: ... and what was cut off at most this share of what is left (a drape's speckle or a large
#: blob of the balls' hue is not a ball with a tail)
TRIM_MAX_CUT = 0.5


def trim_tail(contour: np.ndarray, minor_px: float):
    """The outer contour (OpenCV, int32 (m, 1, 2) px) of the largest part of the blob bounded by
    ``contour`` left after a morphological opening with a disc of radius
    :data:`TRIM_TAIL_SHARE` x ``minor_px`` (the blob's fitted minor semi-axis, px): a contact
    shadow's tail or a thin bridge to a neighbouring blob is cut off, a disc wider than the
    kernel is kept whole. None when the opening changes nothing or leaves nothing."""
    k = int(round(TRIM_TAIL_SHARE * float(minor_px)))
    if k < 2:
        return None
    x, y, bw, bh = cv2.boundingRect(contour)
    m = np.zeros((bh + 2, bw + 2), np.uint8)
    cv2.drawContours(m, [contour], -1, 255, -1, offset=(1 - x, 1 - y))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))
    opened = cv2.morphologyEx(m, cv2.MORPH_OPEN, disc)
    if np.array_equal(m, opened):
        return None
    cs, _ = cv2.findContours(opened, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE, offset=(x - 1, y - 1))
    return max(cs, key=cv2.contourArea) if cs else None


def _trimmed_blob(cnt, inner_area: float, feats: dict, ell, rules: "BlobRules"):
    """A blob that scored too low, trimmed (:func:`trim_tail`) and scored again: (contour, inner
    area px, score, factors, ellipse) as :func:`score_blob` gives them when the trimmed blob
    passes (``min_score``, :data:`TRIM_KEEP_MINOR`, :data:`TRIM_MAX_CUT`), else None. Only a
    blob of a plausible size is tried; its factors record the area cut off
    (``trimmed_area_px``), and it stays out of the frame's size consensus (what a trim left may
    be a fragment). The edge fit that follows judges the ball as any other."""
    if ell is None or feats.get("f_range") != 1.0:
        return None
    trimmed = trim_tail(cnt, ell[1][1])
    if trimmed is None:
        return None
    t_inner = float(cv2.contourArea(trimmed))
    t_score, t_feats, t_ell = score_blob(trimmed, t_inner, rules)
    if (t_score < rules.min_score or t_ell is None or t_ell[1][1] < TRIM_KEEP_MINOR * ell[1][1]
            or inner_area - t_inner > TRIM_MAX_CUT * t_inner):
        return None
    t_feats["trimmed_area_px"] = float(inner_area - t_inner)
    return trimmed, t_inner, t_score, t_feats, t_ell


#: a blob takes a predicted ball's outline shape when its centre lies within this share of its
#: minor semi-axis (at least 2 px) of the predicted centre (the head moves a few px per frame;
#: the shape changes by ~1e-4 per px across the image)
HINT_SHAPE_SHARE = 0.5


#: a blob's edge fit starts its rays from that ball's own fitted centre in the previous frame
#: (``start_px`` of :func:`analyse_blobs`) instead of the blob's pixel-contour ellipse when the
#: two lie within this many px (0 = never). The contour's centre is off by ~0.5 px, and a fit
#: that ends more than ``edge_fit.RECENTRE_PX`` from where its rays started is fitted a second
#: time from its own centre (about half the balls of a frame, half the edge fit's time); last
#: frame's own fit is where that second pass would start for a ball that moved little. Not the
#: pose's prediction: on rendered frames with shading (issue 28) an edge fit depends a little on
#: where its rays start, and rays started from the pose's consensus pulled the balls towards it
#: (PBR tuning crops, clean: target error 0.84 vs 0.42 mm median). A ball further from its last
#: centre (it moved, a new blob) starts from its contour as before; the fit's own checks (how far
#: it may move from the blob) are unchanged.
START_AT_LAST_PX = 1.0


def _started_centres(start_px, ells: list) -> list:
    """The coarse ellipses ((cx, cy), (d1, d2), angle) with each centre replaced by the nearest
    of ``start_px`` ((n, 2) px or None) where that lies within :data:`START_AT_LAST_PX` of it."""
    if start_px is None or len(start_px) == 0 or START_AT_LAST_PX <= 0:
        return list(ells)
    start_px = np.asarray(start_px, float).reshape(-1, 2)
    out = []
    for (cx, cy), axes, ang in ells:
        d = np.hypot(start_px[:, 0] - cx, start_px[:, 1] - cy)
        q = int(np.argmin(d))
        c = (float(start_px[q, 0]), float(start_px[q, 1])) if d[q] <= START_AT_LAST_PX else (cx, cy)
        out.append((c, axes, ang))
    return out


def _hinted_shapes(hint, ells: list) -> list:
    """Per coarse ellipse ((cx, cy), (d1, d2), angle), the outline shape (minor / major, major
    axis deg) of the predicted ball it lies on (:data:`HINT_SHAPE_SHARE`), or None."""
    out: list = [None] * len(ells)
    if hint is None or len(hint) == 0:
        return out
    for j, ((cx, cy), (d1, d2), _a) in enumerate(ells):
        d = np.hypot(hint.centres_px[:, 0] - cx, hint.centres_px[:, 1] - cy)
        q = int(np.argmin(d))
        if d[q] <= max(2.0, HINT_SHAPE_SHARE * min(d1, d2) / 2.0):
            out[j] = (float(hint.axes_px[q, 1] / hint.axes_px[q, 0]), float(hint.angles_deg[q]))
    return out


class _Stages:
    """Wall time (s) per named stage, measured between successive :meth:`lap` calls."""

    def __init__(self):
        self.stages: dict = {}
        self._t = time.perf_counter()

    def lap(self, name: str) -> None:
        t = time.perf_counter()
        self.stages[name] = self.stages.get(name, 0.0) + t - self._t
        self._t = t


def blob_contours(mask: np.ndarray, offset=(0, 0)) -> list:
    """Outer boundaries (OpenCV contours, int32 (m, 1, 2) px) of the blobs of a binary uint8
    ``mask``, shifted by ``offset`` (x, y) px (a window's origin in the image): also those of
    blobs inside a hole of another one (balls on the head seen through a ball-coloured drape
    around it: RETR_EXTERNAL would drop them unseen)."""
    contours, hier = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE,
                                      offset=(int(offset[0]), int(offset[1])))
    return [c for c, hh in zip(contours, hier[0] if hier is not None else []) if hh[3] < 0]


def analyse_blobs(image: np.ndarray, mask: np.ndarray | None, rules: BlobRules, detector: str,
                  refine_image: np.ndarray | None = None, centre_method: str = "edge",
                  edge_blur_px: float | None = None, contours: list | None = None,
                  info: dict | None = None, frame: dict | None = None,
                  hint: "DetectionHint | None" = None, start_px=None, size_peers=()) -> tuple[list, list]:
    """Contours of a binary ``mask`` -> (accepted, rejected) :class:`ImageFiducial` lists.
    ``refine_image`` (default ``image``) is the full-resolution BGR image for sub-pixel centres;
    ``centre_method`` one of :data:`CENTRE_METHODS` (see the module docstring);
    ``edge_blur_px`` the edge fit's blur (px; None = measured in the frame, see
    :func:`~.edge_fit.fit_ball_edges`); ``contours``: the blobs' contours in image px
    (:func:`blob_contours`) instead of ``mask`` (e.g. found in windows only); ``info``: a dict
    that receives ``edge_blur_px`` (the blur the edge fit used, px; None without a fit) and
    ``stages_s`` (wall time s per stage: contours, shape, outline, blur, edge_fit); ``frame``:
    what is known of the frame's imaging, passed to :func:`~.edge_fit.fit_ball_edges` (which
    also stores what it measured there); ``hint``: the balls' predicted ellipses
    (:class:`DetectionHint`): a blob lying on a predicted ball takes that ball's outline shape
    (from the pose: no need to compute it from the blob, :func:`_hinted_shapes`); ``start_px``:
    None or (n, 2) px, the balls' own edge-fit centres in the previous frame of a stream: a blob
    within :data:`START_AT_LAST_PX` of one starts its edge rays there (:func:`_started_centres`);
    ``size_peers``: the minor semi-axes (px) of balls already found in this frame, which join the
    size consensus (a second look at part of a frame judges sizes against the whole frame's)."""
    if centre_method not in CENTRE_METHODS:
        raise ValueError(f"centre_method must be one of {CENTRE_METHODS}, got {centre_method!r}")
    refine_image = image if refine_image is None else refine_image
    h, w = refine_image.shape[:2]
    clock = _Stages()
    if contours is None:
        contours = blob_contours(mask)
    clock.lap("contours")
    cands, rejected = [], []
    for cnt in contours:
        inner_area = cv2.contourArea(cnt)              # area inside the pixel-centre contour
        area = inner_area + 0.5 * len(cnt)             # + half a pixel border: the blob's pixel area
        x, y, bw, bh = cv2.boundingRect(cnt)
        if area < rules.min_area_px:
            continue  # speckle: not worth a rejection record
        if x <= 0 or y <= 0 or x + bw >= w or y + bh >= h:
            rejected.append(ImageFiducial(np.array([x + bw / 2, y + bh / 2]), (bw / 2, bh / 2), 0.0, 0.0, area,
                                          "touches the image border"))
            continue
        _, hi = rules.radius_range_px
        if bw > 3 * hi or bh > 3 * hi:
            rejected.append(ImageFiducial(np.array([x + bw / 2, y + bh / 2]), (bw / 2, bh / 2), 0.0, 0.0, area,
                                          "too large for a fiducial"))
            continue
        score, feats, ell = score_blob(cnt, inner_area, rules)
        if score < rules.min_score and rules.trim_tails:
            trimmed = _trimmed_blob(cnt, inner_area, feats, ell, rules)
            if trimmed is not None:
                cnt, inner_area, score, feats, ell = trimmed
                area = inner_area + 0.5 * len(cnt)
        if centre_method == "chroma":
            ref = refine_blob(refine_image, cnt)
        else:        # the edge fit below gives the centre (and refuses a blob without contrast)
            ref = (np.array(ell[0], float), area, None) if ell is not None else None
        if ell is None or ref is None:
            rejected.append(ImageFiducial(np.array([x + bw / 2, y + bh / 2]), (bw / 2, bh / 2), 0.0, 0.0, area,
                                          feats.get("why", "no contrast")))
            continue
        centre, soft_area, _ = ref
        cands.append(ImageFiducial(centre, ell[1], float(ell[2]), score, soft_area, "", feats))
    # size consensus: balls lie at similar depths, so their minor axes agree (a trimmed blob's
    # size is judged by it, not part of it: what a trim left may be a fragment)
    good = [c.axes_px[1] for c in cands if c.score >= rules.min_score and "trimmed_area_px" not in c.features] \
        + [float(p) for p in size_peers]
    if len(good) >= 3:
        med = float(np.median(good))
        for c in cands:
            rel = abs(c.axes_px[1] - med) / med
            f_size = float(np.exp(-(max(rel - 0.12, 0.0) / 0.12) ** 2))
            c.features["f_size"] = f_size
            c.score *= f_size
    clock.lap("shape")
    edge_fits = {}
    if centre_method == "edge":      # one batch for all candidates that passed the shape test
        good = [i for i, c in enumerate(cands) if c.score >= rules.min_score]
        ells = [cands[i].features["contour_ellipse"] for i in good]
        shapes = None
        if rules.camera is not None:
            problem = rules.camera.frame_size_problem(refine_image.shape)
            if problem:   # the pose tracker refuses such frames first: reaching here is a bug
                raise ValueError(f"ball outlines: {problem}")
            shapes = _hinted_shapes(hint, ells)
            rest = [j for j, sh in enumerate(shapes) if sh is None]
            if rest:
                for j, sh in zip(rest, expected_shapes(rules.camera, [ells[j][0] for j in rest],
                                                       [min(ells[j][1]) / 2.0 for j in rest])):
                    shapes[j] = sh
        clock.lap("outline")
        if edge_blur_px is None and ells:
            edge_blur_px = (measure_edge_blur(refine_image, ells) if edge_fit.MEASURE_BLUR else None) \
                or edge_fit.BLUR_PROBE_PX
        clock.lap("blur")
        fits = fit_ball_edges(refine_image, _started_centres(start_px, ells), edge_blur_px, shapes, frame=frame,
                              shadow_in_px=rules.shadow_in_px, shadow_far_per_radius=rules.shadow_far_per_radius)
        edge_fits = dict(zip(good, fits))
        clock.lap("edge_fit")
    if info is not None:
        info["edge_blur_px"] = edge_blur_px
        info["stages_s"] = clock.stages
    accepted, edge_fitted = [], []   # edge_fitted: (accepted ball, its edge-fit centre px)
    for i, c in enumerate(cands):
        contour_ellipse = c.features.pop("contour_ellipse")   # the colour blob's (cv2.fitEllipse)
        c.features["blob_centre_px"] = (float(contour_ellipse[0][0]), float(contour_ellipse[0][1]))
        fit = edge_fits.get(i)
        if fit is not None:
            c.features.update(edge_rms_px=fit.rms_px, edge_rays_kept=fit.kept, centre_sigma_px=fit.centre_sigma_px,
                              edge_minor_px=fit.axes_px[1])
            if not fit.ok:
                c.reason = fit.reason
                rejected.append(c)
                continue
            c.centre_px = fit.centre_px
            # the second reading of the centre and where a contact shadow lies (the pose
            # tracker's shading check, :mod:`.shading_check`)
            shaded, moved = shaded_centre(refine_image, fit.centre_px, c.features["blob_centre_px"], fit.axes_px[1])
            c.features.update(shading_shift_vec_px=(float(shaded[0] - fit.centre_px[0]),
                                                    float(shaded[1] - fit.centre_px[1])),
                              edge_shadow_rays=fit.shadow_rays, edge_shadow_dir=fit.shadow_dir,
                              highlight_ratio=highlight_ratio(refine_image, fit.centre_px, fit.axes_px[1]))
            if c.score >= rules.min_score:
                edge_fitted.append((c, fit.centre_px))
            if rules.shading_shift:
                c.centre_px = shaded
                c.features["shading_shift_px"] = moved
        if c.score >= rules.min_score:
            accepted.append(c)
        else:
            f = c.features
            worst = min(("f_fit", "boundary not elliptic (cut by an occluder?)"),
                        ("f_round", "not round"), ("f_fill", "not a filled ellipse"),
                        ("f_range", "implausible size for the ball radius"),
                        ("f_size", "size differs from the other balls"),
                        key=lambda kv: f.get(kv[0], 1.0))
            c.reason = f"score {c.score:.2f}: {worst[1]}"
            rejected.append(c)
    if edge_fitted and rules.skin_band_ratio > 0:
        # a band of shadow beside each edge-fitted ball's unlit limb (the shading check's evidence,
        # :mod:`.skin_band`): from its colour blob's outline, read before any shading shift moved it
        ratios = skin_band.band_ratios(refine_image, [p for _, p in edge_fitted],
                                       [float(np.mean(c.axes_px)) for c, _ in edge_fitted],
                                       [c.features["shading_shift_vec_px"] for c, _ in edge_fitted], float(edge_blur_px))
        for (c, _), r in zip(edge_fitted, ratios):
            c.features.update(skin_band_ratio=float(r), skin_band=bool(r < rules.skin_band_ratio))
    accepted.sort(key=lambda c: (c.centre_px[1], c.centre_px[0]))
    return accepted, rejected
