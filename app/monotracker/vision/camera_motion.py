"""Has the camera moved since tracking started? Watch the static background.

Why: the registration is to the camera (``T_cam_ct``) and the arm reaches the head through the
hand-eye ``T_base_cam``. If the camera is bumped or its stand sags after the hand-eye
calibration, every pose stays consistent (residuals, FRE and predicted TRE are unchanged) while
the arm follows a path that is off by the camera's motion: 1.5 deg at 450 mm is ~12 mm. Nothing
in the fiducials can show it; the room can. A camera that turns by ``theta`` shifts the whole
background by about ``f * theta`` px (1100 px focal length: 19 px per degree), a camera that
shifts by ``d`` mm moves a background ``D`` mm away by ``f * d / D`` px.

How (:class:`CameraMotionMonitor`): at the first usable frame it keeps a reference of the
background (grey, half resolution, high-passed and normalised so that a global lighting change
does not look like motion) and up to ``max_features`` corners outside the head (a disc around
the fiducials given by the caller). Every ``every_n_frames`` it tracks those corners from the
reference into the frame (pyramidal Lucas-Kanade) and fits one
similarity transform to them with RANSAC: the background's motion, robust to the head, hands,
instruments or the arm moving in front of part of it. ``shift_px`` is the largest displacement
that transform gives over the background's extent (full-resolution px); ``angle_deg`` the camera rotation
that shift means (``shift_px / f``). The camera counts as moved when ``shift_px`` exceeds
``alarm_px`` in ``confirm_checks`` checks in a row (or ``immediate_px`` once), with at least ``min_inliers`` corners and
``min_inlier_share`` of the tracked ones agreeing; it stays moved (latched) until :meth:`reset`
(after the camera was put back and the hand-eye re-checked). When too few corners agree (the
background covered, the lights off) the monitor says it cannot check (``checking`` False) rather
than guess, and keeps its reference until the background agrees again; when part of the
background changes for good (a drape moved), it re-anchors on a frame it tracked well, carrying the
motion found so far over.

Units: px (full-resolution image), deg. Limits (measured in ``benchmarks/camera_motion.py``):
a background with texture is needed (drapes, the head clamp, the table edge); a camera moved
before tracking started (between the hand-eye calibration and the camera's start) is invisible to
it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class MotionConfig:
    """Settings of :class:`CameraMotionMonitor` (px are full-resolution image pixels)."""

    #: check one frame in this many (the others cost nothing)
    every_n_frames: int = 3
    #: work at this share of the image size (a quarter: the sensor noise averages out over 4 x 4
    #: pixels, the drape's texture stays, a check costs ~2 ms at 1280x720)
    scale: float = 0.25
    max_features: int = 150
    #: a background shift over this (px) counts; 2 px is 0.1 deg at f = 1100 px (0.8 mm at 450 mm)
    alarm_px: float = 2.0
    #: ... in this many checks in a row; a shift over ``immediate_px`` (a knock: 1.5 deg is ~30 px)
    #: counts at once
    confirm_checks: int = 2
    immediate_px: float = 8.0
    #: RANSAC inlier threshold (px, full resolution)
    ransac_px: float = 3.0
    min_inliers: int = 20
    min_inlier_share: float = 0.4
    #: a tracked corner whose patch differs from the reference by more than this times the
    #: median (LK's error) is taken as covered and left out
    patch_error_factor: float = 2.5
    #: re-anchor (new reference, the motion so far carried over) only when fewer than this share
    #: of the reference's corners agree: each re-anchor adds its estimate's error (~0.2-0.5 px),
    #: so a hand passing over the drape must not cause one
    reanchor_share: float = 0.3
    #: the head is excluded: a disc around the fiducials' centroid of their largest distance
    #: from it times this, plus ``head_margin_px``
    head_scale: float = 2.0
    head_margin_px: float = 60.0


@dataclass
class MotionReport:
    """One check: ``checking`` (enough background agreed), ``shift_px`` (largest displacement of
    the background transform inside the image, full-res px; NaN when not checking),
    ``angle_deg`` (``shift_px / f`` in degrees), ``inliers`` / ``tracked`` corners, ``moved``
    (latched verdict), ``reason`` (one line when moved or not checking)."""

    checking: bool
    shift_px: float
    angle_deg: float
    inliers: int
    tracked: int
    moved: bool
    reason: str = ""


def _prepare(image: np.ndarray, scale: float) -> np.ndarray:
    """Grey, resized, high-passed and normalised (uint8 around 128): a global gain or offset
    change of the lighting leaves it unchanged."""
    # grey first, then the area average: both linear, so the same image as the other order up to
    # rounding, at a third of the cost (resizing three channels was 1.8 of a check's ~4.8 ms)
    g = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    if scale != 1.0:
        g = cv2.resize(g, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    g = g.astype(np.float32)
    hp = g - cv2.GaussianBlur(g, (0, 0), 4.0)
    s = float(cv2.mean(np.abs(hp))[0]) + 1e-3
    return np.clip(128.0 + 30.0 * hp / s, 0, 255).astype(np.uint8)


class CameraMotionMonitor:
    """See the module docstring. ``focal_px``: the camera's focal length (px, full resolution),
    for the angle; ``config``: :class:`MotionConfig`. Not thread-safe: one pose pipeline feeds it."""

    def __init__(self, focal_px: float, config: MotionConfig | None = None):
        self.focal_px = float(focal_px)
        self.config = config or MotionConfig()
        self.reset()

    def reset(self) -> None:
        """Forget the reference and the verdict: the camera is where the hand-eye says it is."""
        self._ref = None              # prepared reference image
        self._pts = None              # (n, 1, 2) float32 corners in the reference (work scale)
        self._A_ref = np.eye(3)       # reference -> rest (3x3 similarity, full-res px)
        self._frames = 0
        self._over = 0
        self.moved = False
        self.last: MotionReport | None = None
        self.max_shift_px = 0.0       # largest shift seen so far (full-res px), for the record

    # ------------------------------------------------------------------ main entry
    def update(self, image: np.ndarray, fiducials_px: np.ndarray | None = None,
               force: bool = False) -> MotionReport | None:
        """Feed one frame (BGR or grey uint8); ``fiducials_px`` (n, 2) the balls' image positions
        (full-res px; NaN rows ignored) to keep the head out of the background; ``force``: check
        this frame although ``every_n_frames`` would skip it (the pose jumped: a knock?). Returns
        the check's :class:`MotionReport`, or None on frames that are not checked."""
        cfg = self.config
        self._frames += 1
        if self._ref is not None and not force and (self._frames - 1) % max(1, cfg.every_n_frames):
            return None
        return self._check_frame(image, fiducials_px)

    def next_is_checked(self) -> bool:
        """Whether the next :meth:`update` checks its frame (the others only count it)."""
        return self._ref is None or self._frames % max(1, self.config.every_n_frames) == 0

    def _check_frame(self, image: np.ndarray, fiducials_px) -> MotionReport:
        cfg = self.config
        img = _prepare(image, cfg.scale)
        if self._ref is None:
            return self._anchor(img, fiducials_px)
        return self._check(img, fiducials_px)

    def _head_disc(self, fiducials_px):
        """(centre (2,), radius) full-res px of the disc kept out of the background: around the
        balls' median, ``head_scale`` x the 80th percentile of their distances from it plus
        ``head_margin_px`` (a stray blob far away does not blow it up); None without balls."""
        if fiducials_px is None:
            return None
        p = np.asarray(fiducials_px, float).reshape(-1, 2)
        p = p[np.all(np.isfinite(p), axis=1)]
        if len(p) == 0:
            return None
        c = np.median(p, axis=0)
        d = np.linalg.norm(p - c, axis=1)
        return c, self.config.head_scale * float(np.percentile(d, 80)) + self.config.head_margin_px

    def _head_mask(self, shape, fiducials_px) -> np.ndarray:
        cfg = self.config
        mask = np.full(shape, 255, np.uint8)
        disc = self._head_disc(fiducials_px)
        if disc is not None:
            c, r = disc
            cv2.circle(mask, tuple(int(round(v * cfg.scale)) for v in c), int(round(r * cfg.scale)), 0, -1)
        return mask

    def _anchor(self, img: np.ndarray, fiducials_px, carried: np.ndarray | None = None) -> MotionReport:
        cfg = self.config
        pts = cv2.goodFeaturesToTrack(img, cfg.max_features, 0.01, 6, mask=self._head_mask(img.shape, fiducials_px),
                                      blockSize=7)
        if pts is None or len(pts) < cfg.min_inliers:
            self._ref = None
            return self._report(False, np.nan, 0, 0 if pts is None else len(pts),
                                "camera motion not checked: too little background texture outside the head")
        self._ref, self._pts = img, pts.astype(np.float32)
        if carried is not None:
            self._A_ref = carried
        shift = self._shift(self._A_ref)
        return self._report(True, shift, len(pts), len(pts), "")

    def _check(self, img: np.ndarray, fiducials_px) -> MotionReport:
        cfg = self.config
        # the reference's pyramid is built once (at the anchor); 2 levels of a 21 px window follow
        # shifts up to ~150 px full-resolution (a knock of ~7 deg)
        lk = dict(winSize=(21, 21), maxLevel=2, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.02))
        p0 = self._pts
        p1, st1, err = cv2.calcOpticalFlowPyrLK(self._ref, img, p0, None, **lk)
        if p1 is None:
            return self._lost(img, fiducials_px, 0, 0)
        ok = st1.ravel() == 1
        e = err.ravel()
        if ok.sum() >= cfg.min_inliers:   # a corner whose patch no longer matches is covered (a hand, a tool)
            ok &= e <= cfg.patch_error_factor * float(np.median(e[ok]))
        disc = self._head_disc(fiducials_px)
        if disc is not None:      # the head moved over part of the background: leave those corners out
            c, r = disc
            now = p1.reshape(-1, 2) / cfg.scale
            ok &= np.linalg.norm(now - c, axis=1) > r
        n_tracked = int(ok.sum())
        if n_tracked < cfg.min_inliers:
            return self._lost(img, fiducials_px, 0, n_tracked)
        a = p0.reshape(-1, 2)[ok] / cfg.scale
        b = p1.reshape(-1, 2)[ok] / cfg.scale
        M, inl = cv2.estimateAffinePartial2D(a, b, method=cv2.RANSAC, ransacReprojThreshold=cfg.ransac_px,
                                             maxIters=500, confidence=0.995)
        n_in = 0 if inl is None else int(inl.sum())
        if M is None or n_in < cfg.min_inliers or n_in < cfg.min_inlier_share * n_tracked:
            return self._lost(img, fiducials_px, n_in, n_tracked)
        A_now_ref = np.vstack([M, [0.0, 0.0, 1.0]])
        total = A_now_ref @ self._A_ref
        shift = self._shift(total)
        if n_in < cfg.reanchor_share * len(p0):   # the background changed for good: re-anchor, keep the motion
            self._anchor(img, fiducials_px, carried=total)
        return self._report(True, shift, n_in, n_tracked, "")

    def _lost(self, img, fiducials_px, n_in: int, n_tracked: int) -> MotionReport:
        """Too few corners agree: no verdict from this frame. The reference is kept (the
        background may come back); a new one taken now could hide a motion made meanwhile."""
        self._over = 0
        return self._report(False, np.nan, n_in, n_tracked,
                            "camera motion not checked: too few background points agree (background covered?)")

    def _shift(self, A: np.ndarray) -> float:
        """Largest displacement (full-res px) that the 3x3 similarity ``A`` makes at the corners
        and centre of the box the reference's background corners span (not beyond: there the
        fitted rotation and scale would be extrapolated)."""
        if self._pts is None:
            return 0.0
        p = self._pts.reshape(-1, 2) / self.config.scale
        (x0, y0), (x1, y1) = p.min(axis=0), p.max(axis=0)
        P = np.array([[x0, y0, 1], [x1, y0, 1], [x0, y1, 1], [x1, y1, 1], [(x0 + x1) / 2, (y0 + y1) / 2, 1]])
        return float(np.max(np.linalg.norm((P @ A.T)[:, :2] - P[:, :2], axis=1)))

    def _report(self, checking: bool, shift: float, n_in: int, n_tracked: int, reason: str) -> MotionReport:
        cfg = self.config
        if checking:
            self.max_shift_px = max(self.max_shift_px, shift)
            self._over = self._over + 1 if shift > cfg.alarm_px else 0
            if self._over >= cfg.confirm_checks or shift > cfg.immediate_px:
                self.moved = True
        angle = float(np.degrees(shift / self.focal_px)) if np.isfinite(shift) else float("nan")
        if self.moved:
            big = self.max_shift_px
            reason = (f"the camera moved since tracking started: the background shifted {big:.1f} px "
                      f"(about {np.degrees(big / self.focal_px):.2f} deg): the hand-eye calibration no longer holds, so the arm would "
                      "follow a wrong path; put the camera back and redo the hand-eye calibration, then restart "
                      "the camera")
        self.last = MotionReport(checking, shift, angle, n_in, n_tracked, self.moved, reason)
        return self.last


class DeferredMotionWatch:
    """A :class:`CameraMotionMonitor` whose checks run after the frame's pose was given out
    (issue 29): the check of a due frame (~2.5-3 ms of CPU at 1280x720, one frame in
    ``every_n_frames``) is kept by :meth:`defer` and run by :meth:`run_pending`, which the pose
    pipeline calls once it has published that frame's estimate, in the time before the next
    frame arrives. The frame's own path then carries no check, and nothing runs beside it to slow
    it down (the check on a worker thread beside the detection, the design before, cost the
    frame 1-2.5 ms of its own CPU on two cores: the demo's latency p95 went over 45 ms with it).

    What that costs in safety, and why it is small: the verdict of a due frame counts from the
    next frame (+1 frame, 33 ms at 30 fps). A knock still stops the frame it happens in: a pose
    that jumped more than ``TrackerConfig.motion_jump_mm`` from the last trusted one is checked at
    once, on its frame's path, due or not (:class:`~.pose_tracker.PoseTracker`); a slow sag
    needs ``confirm_checks`` checks over the alarm anyway (>= 6 frames at the engine's every 6th
    frame), and frames that are not due were never checked on their own path. A pipeline that
    does not call :meth:`run_pending` gets the check run at the start of its next frame (the
    tracker does it before it judges that frame): the verdict is never skipped.

    The same verdict interface as the monitor (``moved``, ``last``, ``max_shift_px``,
    ``next_is_checked``, ``update``, ``reset``); ``check_cpu_s``: CPU time (s) of the last check
    run by :meth:`run_pending`. The image given to :meth:`defer` must not be written to until the
    check ran (frames are never modified once captured). Not thread-safe: one pose pipeline uses it.
    """

    def __init__(self, monitor: CameraMotionMonitor):
        self.monitor = monitor
        self._pending: tuple[np.ndarray, np.ndarray | None] | None = None
        #: CPU time (s) of the last check run by :meth:`run_pending`
        self.check_cpu_s = 0.0

    # the monitor's verdict, as of the checks run so far
    @property
    def moved(self) -> bool:
        return self.monitor.moved

    @property
    def last(self) -> MotionReport | None:
        return self.monitor.last

    @property
    def max_shift_px(self) -> float:
        return self.monitor.max_shift_px

    @property
    def pending(self) -> bool:
        """A deferred check waits to be run."""
        return self._pending is not None

    def next_is_checked(self) -> bool:
        """Whether the next frame fed is a due one (see :meth:`CameraMotionMonitor.next_is_checked`)."""
        return self.monitor.next_is_checked()

    def defer(self, image: np.ndarray, fiducials_px: np.ndarray | None) -> None:
        """Keep this frame (and its balls, (n, 2) px, NaN rows ignored, copied) for
        :meth:`run_pending`: the frame counts when its check runs. A check still waiting is run
        first, so the monitor sees the frames in order."""
        self.run_pending()
        pts = None if fiducials_px is None else np.array(fiducials_px, dtype=float, copy=True).reshape(-1, 2)
        self._pending = (image, pts)

    def run_pending(self) -> MotionReport | None:
        """Run the deferred check, if any (its verdict then shows in ``moved`` / ``last``; its CPU
        time in ``check_cpu_s``); raises what the check raised (the caller's error path)."""
        if self._pending is None:
            return None
        (image, pts), self._pending = self._pending, None
        c0 = time.thread_time()
        try:
            return self.monitor.update(image, pts)
        finally:
            self.check_cpu_s = time.thread_time() - c0

    def update(self, image: np.ndarray, fiducials_px: np.ndarray | None = None,
               force: bool = False) -> MotionReport | None:
        """The monitor's :meth:`CameraMotionMonitor.update`, inline (after a deferred check)."""
        self.run_pending()
        return self.monitor.update(image, fiducials_px, force=force)

    def reset(self) -> None:
        """Drop a deferred check, then forget the reference and the verdict (see
        :meth:`CameraMotionMonitor.reset`)."""
        self._pending = None
        self.monitor.reset()
