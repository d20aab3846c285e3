"""What the per-frame pose stream gives out: :class:`PoseEstimate` (one frame's pose, its trust
verdict and the balls' statuses), the per-fiducial status words and the camera states' alert codes.
Data only: :mod:`.pose_tracker` makes them."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SEEN, NEWLY_LOST, OCCLUDED, UNKNOWN, MOVED = "seen", "newly_lost", "occluded", "unknown", "moved"

#: camera state -> alert code of the invalid estimate it causes
#: ("late": a live camera's read() waits longer than a frame should take, the source alive;
#: "stalled": it waited much longer, the camera stopped delivering; "frozen": identical frames)
CAMERA_CODES = {"frozen": "camera_freeze", "late": "camera_late", "stalled": "camera_stalled",
                "disconnected": "camera_disconnected", "ended": "camera_ended", "unreadable": "frame_unreadable"}



@dataclass
class PoseEstimate:
    """One published result. Times are ``time.monotonic()`` seconds; ``latency_s`` is
    publication time minus capture time. ``T_cam_ct`` (4x4, mm) is None when ``ok`` is False.
    ``status`` has one entry per CT fiducial (the words above; :mod:`.fiducial_states`); ``image_points_px`` holds
    the matched detection per CT fiducial (NaN where none) and ``residuals_px`` its
    reprojection error (NaN where none). ``predicted_tre_mm`` is at the planned target (NaN if
    no target was given or no pose). ``alerts`` are one-line operator messages for this frame.
    ``camera`` is "ok", "frozen", "late", "stalled", "disconnected" or "ended". ``detect_s`` /
    ``register_s`` are the stage times (s); ``truth`` is the simulator's ground truth of the
    frame (None for real cameras), carried for overlays and benchmarks.

    Attributes:
        ok: True when the pose passed every gate of :mod:`.pose_tracker`'s docstring; when False the
            controller holds and ``code`` / ``reason`` say why.
        reason: one line for the operator ("" when ok).
        frame_index: index of the frame in its source.
        t_capture, t_published: ``time.monotonic()`` s of capture and of publication.
        T_cam_ct: (4, 4) float64, CT LPS mm -> OpenCV camera mm; None when not ok.
        status: n strings, one per CT fiducial: "seen", "newly_lost", "occluded", "unknown",
            "moved".
        image_points_px: (n, 2) float, px: the matched detection per CT fiducial, NaN where none.
        residuals_px: (n,) float, px: reprojection error per CT fiducial, NaN where none.
        fre_mm: monocular FRE of the fit, mm (NaN without a pose).
        reprojection_rms_px: RMS reprojection error of the fit, px (NaN without a pose).
        predicted_tre_mm: predicted RMS error at the planned target, mm (NaN without a target
            or a pose).
        n_detected, n_matched: balls detected in the image; of those, matched to fiducials.
        alerts: one-line operator messages raised in this frame.
        camera: "ok", "frozen", "late", "stalled", "disconnected" or "ended".
        used_prior: the registration's prior fast path produced the pose.
        detect_s, register_s: stage times, s (``register_s``: registration and screening).
        stages_s: wall time (s) per stage of this frame: ``hint`` (the balls' predicted
            ellipses for the detector), ``detect``, ``register`` (the first
            registration), ``average`` (the mean of a still view's frames, 0 without it:
            :mod:`.still_frames`), ``screen`` (the moved-fiducial screening after it), ``gates`` (the
            checks after the registration, to the estimate), ``motion`` (the camera-motion
            watch's share of this frame, 0 without one); and ``detect.<stage>`` for the
            detector's own stages (:attr:`~.detection.Detection.stages_s`).
        truth: the simulator's ground truth of the frame, or None (real cameras).
        code: alert code when not ok ("frame_size", "camera_freeze", "occlusion", "pose_lost",
            "pose_implausible", "weak_geometry", "tre_limit", ...); "" when ok.
        sigma_px, sigma_source: image noise (px) behind ``predicted_tre_mm`` and its origin.
        moved: [(fiducial index, shift mm)] found moved in this frame.
        excluded: indices of every fiducial excluded so far (moved).
    """

    ok: bool
    reason: str
    frame_index: int
    t_capture: float
    t_published: float
    T_cam_ct: np.ndarray | None = None
    status: list = field(default_factory=list)
    image_points_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    residuals_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    fre_mm: float = float("nan")
    reprojection_rms_px: float = float("nan")
    predicted_tre_mm: float = float("nan")
    n_detected: int = 0
    n_matched: int = 0
    alerts: list = field(default_factory=list)
    camera: str = "ok"
    used_prior: bool = False
    detect_s: float = float("nan")
    register_s: float = float("nan")
    stages_s: dict = field(default_factory=dict)
    truth: object = None
    #: alert code when not ok (:mod:`.pose_tracker`'s docstring lists them); "" when ok
    code: str = ""
    #: image noise (px) behind ``predicted_tre_mm`` and where it came from (OnlineNoise.source)
    sigma_px: float = float("nan")
    sigma_source: str = ""
    #: fiducials found moved in this frame: [(fiducial index, shift mm)]
    moved: list = field(default_factory=list)
    #: all fiducials excluded so far (moved), by index
    excluded: list = field(default_factory=list)
    #: frames of a still head pooled into ``T_cam_ct`` (1 = this frame alone; 0 when not ok)
    pooled_frames: int = 0
    #: fiducials whose centre in this pose came from an earlier frame of the still head
    #: (:mod:`.ball_memory`; their ``status`` says whether this frame found them: it did not)
    remembered: list = field(default_factory=list)
    #: frames of a still view whose mean the detector read (:mod:`.still_frames`,
    #: ``TrackerConfig.average_still_frames``, at most that many: beyond it the mean weighs the
    #: newest frame 1 / that; 1 = this frame alone)
    averaged_frames: int = 1
    #: balls found in this frame but left out of its pose because the others put them beyond
    #: their cover (``TrackerConfig.disagreement_quantile``): [(fiducial index, px from where the
    #: others put it)]; their ``status`` is "seen"
    set_aside: list = field(default_factory=list)

    @property
    def latency_s(self) -> float:
        return self.t_published - self.t_capture

    @property
    def newly_lost(self) -> list[int]:
        return [i for i, s in enumerate(self.status) if s == NEWLY_LOST]
