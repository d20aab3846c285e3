"""One frame of the live pose stream: detected balls -> registration -> gated, timestamped
PoseEstimate (:class:`PoseTracker`, no threads; :mod:`.pose_stream` runs it on a frame source).

Validity rules (the downstream controller holds whenever ``ok`` is False):
* fewer than ``min_fiducials`` (4) matched balls -> "no valid pose";
* reprojection RMS over ``max_rms_px`` (1.5 px) or any matched ball's residual over
  ``max_residual_px`` (3 px) -> "no valid pose" (the match is suspect);
* camera frozen / stalled / disconnected / ended, an unreadable frame -> "no valid pose";
* a frame whose size differs from the calibration's ``image_size`` -> refused (``frame_size``;
  adapt the calibration explicitly with ``CameraModel.adapted("bin:2")`` etc. when the camera
  is the same sensor binned or cropped);
* the camera moved since tracking started (``camera_motion``, a
  :class:`~.camera_motion.CameraMotionMonitor` watching the static background; off when None)
  -> refused until that monitor is reset (``camera_moved``): the hand-eye no longer holds;
* a grayscale frame (one channel, or three equal ones: a monochrome camera, a grayscale file)
  -> refused (``frame_grayscale``, :func:`.frames.grayscale_problem`): the balls are found by
  their colour;
* a pose that is not physical (head distance, fiducials behind the camera, ball size vs
  distance; :mod:`.pose_checks`) -> ``pose_implausible``; matched balls too few, collinear or
  coplanar -> ``weak_geometry``;
* predicted TRE at the planned target over ``max_predicted_tre_mm`` (1 mm) -> ``tre_limit``.
  The image noise behind it is estimated online from the residuals
  (:class:`~monotracker.registration.noise.OnlineNoise`: pooled over frames, no floor); the
  gate uses the noise's 95 % upper bound for its degrees of freedom (few balls or the first
  frames: a wider bound), ``predicted_tre_mm`` the calibrated value. The same bound must keep
  the probability that the error at the target exceeds ``wrong_mm`` (2 mm) below
  ``max_wrong_probability`` (0.1 %): an RMS limit alone leaves a tail. Each matched ball's
  centre error counts as at least its edge fit's residual RMS, plus a shift common to all balls
  (``edge_bias_per_rms``, ``edge_common_per_rms``): shading moves the centres in a way a slightly
  wrong pose explains, which the residuals cannot show (issue 28). A ball the others put
  more than its cover allows from where it was found (a linearised leave-one-out,
  :mod:`monotracker.registration.disagreement`, ``disagreement_quantile``) is set aside for the
  frame (``set_aside``; at least 5 balls remain) or else covered by that disagreement, and
  named;
* a fiducial whose position disagrees with the others by a shift of >= 1 mm (leave-one-out,
  :mod:`monotracker.registration.consistency`) is excluded with a ``fiducial_moved`` alert
  naming it and the estimated shift (mm), and stays excluded until :meth:`PoseTracker.reset`.

Every invalid estimate carries ``code``: the alert code that says what happened
(``frame_size``, ``frame_grayscale``, ``camera_moved``, ``frame_unreadable``, ``camera_ended``, ``camera_freeze``, ``camera_late``, ``camera_stalled``,
``camera_disconnected``, ``occlusion``, ``pose_lost``, ``pose_implausible``,
``weak_geometry``, ``tre_limit``).

Per-fiducial status (one entry per CT fiducial): ``"seen"`` (matched in this frame),
``"newly_lost"`` (matched in the previous frame, not now: an alert is raised in this same
frame), ``"occluded"`` (not matched now nor in the previous frame), ``"unknown"`` (no frame
has matched it yet). When the registration fails, a ball counts as seen if a detection lies
within ``status_gate_px`` of its projection under the last valid pose. ``"moved"``: the
fiducial was found displaced relative to the others and is excluded.
"""

from __future__ import annotations

import time
import numpy as np

from monotracker.geometry import apply_transform

from .camera_model import CameraModel
from .frame_trust import FrameTrust
from .fiducial_states import FiducialStates
from .frames import Frame, grayscale_problem
from .pooled_trust import PooledTrust
from .pose_estimate import (  # noqa: F401 - the status words stay public names here
    CAMERA_CODES, MOVED, NEWLY_LOST, OCCLUDED, SEEN, UNKNOWN, PoseEstimate)
from .sphere_outline import SphereEllipseCache
from .still_frames import StillFrames, ball_windows
from .tracker_config import (  # noqa: F401 - public names of the pose stream's settings
    SHADING_READINGS, TrackerConfig, few_ball_factor, tail_problem)


class PoseTracker:
    """Per-frame detect + register + status logic (no threads).

    Args:
        fiducials_ct: (n, 3) float, CT LPS mm: the fiducial centres (e.g. from
            :func:`monotracker.ct.detect_fiducials`).
        camera: the calibrated :class:`CameraModel`; frames of another size are refused.
        detector: any object with ``detect(image) -> Detection`` (image points in px); None
            builds the classical colour detector for ``radius_mm`` and the camera's focal length.
            A detector with :class:`~.detection.BlobRules` (``rules``) gets ``camera`` there:
            its edge fits then take each ball's outline from the camera (:mod:`.sphere_outline`).
        radius_mm: ball radius, mm (the registration corrects the ellipse-centre bias with it).
        target_ct: (3,) float, CT LPS mm: planned target for ``predicted_tre_mm``, or None.
        config: the gates (:class:`TrackerConfig`); defaults when None.
        watch_ct: (m, 3) float, CT LPS mm, or None: further balls (validation fiducials) that are
            not registered but whose predicted ellipses go into the detector's hint (indices
            n .. n+m-1), so that a detector searching windows finds them too.
        camera_motion: a :class:`~.camera_motion.CameraMotionMonitor` (the camera must not move
            after the hand-eye calibration; its verdict counts from the frame it checks), a
            :class:`~.camera_motion.DeferredMotionWatch` (the same checks, a due frame's run by
            :meth:`after_publish` once its pose is out, its verdict from the next frame: what
            the engine's rigs use) or None (not watched).

    The detector is called ``detect(image, hint)`` (a detector whose ``detect`` takes no
    ``hint`` is called ``detect(image)``): ``hint`` is a :class:`~.detection.DetectionHint`
    from the last trusted pose while it is fresh (:attr:`TrackerConfig.hint_max_age_frames`;
    every :attr:`TrackerConfig.full_search_every` frames with ``search_all``: the whole frame
    searched), None (a cold full-frame search) otherwise.

    :meth:`process` never raises for a bad frame: it returns ``ok=False`` with a ``code``.
    """

    def __init__(self, fiducials_ct: np.ndarray, camera: CameraModel, detector=None, radius_mm: float = 4.0,
                 target_ct: np.ndarray | None = None, config: TrackerConfig | None = None,
                 watch_ct: np.ndarray | None = None, camera_motion=None):
        from .detect_classical import ClassicalDetector
        from .detection import BlobRules

        self.fiducials_ct = np.asarray(fiducials_ct, float).reshape(-1, 3)
        self.camera = camera
        self.radius_mm = float(radius_mm)
        self.detector = detector or ClassicalDetector(BlobRules(radius_mm=radius_mm, focal_px=float(camera.K[0, 0])))
        rules = getattr(self.detector, "rules", None)
        if isinstance(rules, BlobRules):
            rules.camera = camera   # ball edges fitted with a whole sphere's outline (sphere_outline)
        self.target_ct = None if target_ct is None else np.asarray(target_ct, float).reshape(3)
        self.config = config or TrackerConfig()
        #: the static-background watch (:class:`~.camera_motion.CameraMotionMonitor`) or None
        self.camera_motion = camera_motion
        #: an error of a camera-motion check run by :meth:`after_publish`, raised by the next
        #: :meth:`process` (the caller's error path: that frame is refused, the arm holds)
        self._check_error: BaseException | None = None
        self.watch_ct = np.zeros((0, 3)) if watch_ct is None else np.asarray(watch_ct, float).reshape(-1, 3)
        self._takes_hint = _takes_hint(self.detector)
        #: the hint's predicted ellipses, each reused between frames while its ball moved little
        self._hint_ellipses = SphereEllipseCache()
        self._last_full_index = -(10**9)
        from monotracker.registration.noise import OnlineNoise

        n = len(self.fiducials_ct)
        #: each fiducial's state over the frames (:mod:`.fiducial_states`)
        self.states = FiducialStates(n)
        self._last_T = None
        self._last_T_time = -np.inf
        self._last_T_index = -10
        self._last_ok = None
        self._last_code = ""
        #: fiducial index -> estimated shift (mm) of the balls excluded as moved (persistent)
        self.excluded: dict[int, float] = {}
        c = self.config
        self.noise = OnlineNoise(window=c.noise_window, min_dof=c.noise_min_dof, prior_px=c.noise_prior_px,
                                 prior_is_bound=c.noise_prior_is_bound)
        from .centre_bias import centre_bias_of
        from .still_pool import StillPool

        self.pool = StillPool(max_frames=c.pool_frames, alpha=c.pool_alpha)
        from .ball_memory import StillBallMemory

        #: the balls of the last frames of a still head (:mod:`.ball_memory`)
        self.memory = StillBallMemory(max_age_frames=c.remember_frames if c.centre_bias is None else 0,
                                      min_agreeing=c.min_fiducials)
        #: the centre bias the trust model covers (None: the trust model before issue 28)
        self.centre_bias = centre_bias_of(self.detector) if c.centre_bias == "detector" else c.centre_bias
        #: the trust model of one frame's fit (:mod:`.frame_trust`; the default) and of a still
        #: head's pooled frames (:mod:`.pooled_trust`; with ``centre_bias`` set)
        self.trust = FrameTrust(c, camera, self.fiducials_ct, self.radius_mm, self.memory, self._hint_ellipses)
        self.pooled = PooledTrust(c, camera, self.fiducials_ct, self.radius_mm, self.centre_bias, self.pool)
        #: the mean of a still view's frames the detector reads (None: each frame as it is, or a
        #: detector that reads no image: ``reads_image`` False, e.g. given points)
        self.still_frames = StillFrames(c.average_still_frames, min_noise_dn=c.average_min_noise_dn) \
            if c.average_still_frames > 1 and getattr(self.detector, "reads_image", True) else None
        #: the last detection's balls, accepted or refused: (m, 3) centre and radius px
        self._ball_windows = np.zeros((0, 3))
        from monotracker.registration import pnp_kernels

        pnp_kernels.warm_up()   # compile or load the pose refinement now, not in the first frame's budget

    def reset(self) -> None:
        """Forget the previous frames, the noise estimate and the excluded (moved) fiducials:
        for a new registration after the operator re-checked the fiducials. The camera-motion
        watch keeps its reference (only a new hand-eye clears it: ``camera_motion.reset()``)."""
        self.__init__(self.fiducials_ct, self.camera, self.detector, self.radius_mm, self.target_ct, self.config,
                      self.watch_ct, self.camera_motion)

    def _jumped(self, T_cam_ct: np.ndarray) -> bool:
        """The fiducials' centroid under ``T_cam_ct`` (4x4, CT -> camera, mm) lies more than
        :attr:`TrackerConfig.motion_jump_mm` from where the last trusted pose put it."""
        if self._last_T is None:
            return False
        c = self.fiducials_ct.mean(axis=0)[None]
        return float(np.linalg.norm(apply_transform(T_cam_ct, c)[0] - apply_transform(self._last_T, c)[0])) \
            > self.config.motion_jump_mm

    def after_publish(self) -> float:
        """Run the work this tracker deferred until the last frame's estimate was given out: the
        camera-motion check of a due frame (a :class:`~.camera_motion.DeferredMotionWatch`).
        A pose pipeline calls it right after it published the estimate, in the time before the
        next frame; :meth:`process` runs whatever was left undone before it judges the next frame.
        Returns the CPU time (s) it took (0.0 when nothing was due). Never raises: an error of
        the check is raised by the next :meth:`process`."""
        watch = self.camera_motion
        if watch is None or not getattr(watch, "pending", False):
            return 0.0
        try:
            watch.run_pending()
        except Exception as exc:  # noqa: BLE001 - handed to the next process() call
            self._check_error = exc
        return watch.check_cpu_s   # measured by the watch, also when the check raised

    def _run_deferred_check(self) -> None:
        """Before a frame is judged: raise the error of a check run after the last frame, or run
        the check the pipeline left undone (its verdict counts for this frame)."""
        exc, self._check_error = self._check_error, None
        if exc is not None:
            raise exc
        watch = self.camera_motion
        if watch is not None and getattr(watch, "pending", False):
            watch.run_pending()

    def set_target(self, target_ct: np.ndarray | None) -> None:
        """Planned target, (3,) CT LPS mm, for ``predicted_tre_mm`` (None: no target)."""
        self.target_ct = None if target_ct is None else np.asarray(target_ct, float).reshape(3)

    def process(self, frame: Frame) -> PoseEstimate:
        """Detect, register and gate one frame.

        Args:
            frame: a :class:`~monotracker.vision.frames.Frame` (``image`` of the calibrated
                size, ``index``, ``t_capture`` monotonic s).

        Returns:
            the :class:`PoseEstimate` of this frame.

        Refuses (ok=False, code): frame size differs from the calibration (``frame_size``);
        a grayscale frame (``frame_grayscale``);
        the registration refused, or its RMS or a residual is over the gates (``pose_lost``);
        fewer than ``min_fiducials`` matched (``occlusion``); an implausible pose
        (``pose_implausible``); too few,
        collinear or coplanar matched balls (``weak_geometry``); the predicted error at the
        target over the gates of :class:`TrackerConfig` (``tre_limit``).
        """
        from monotracker.registration.consistency import register_screened
        from .pose_checks import PhysicalLimits, physical_problem, weak_geometry

        cfg = self.config
        n = len(self.fiducials_ct)
        size_problem = self.camera.frame_size_problem(frame.image.shape)
        if size_problem:
            return self._invalid(frame.index, frame.t_capture, "frame_size", size_problem, truth=frame.truth)
        grey = grayscale_problem(frame.image)
        if grey:
            return self._invalid(frame.index, frame.t_capture, "frame_grayscale", grey, truth=frame.truth)
        fresh = (frame.index == self._last_T_index + 1 or frame.t_capture - self._last_T_time <= cfg.prior_max_age_s)
        prior = self._last_T if fresh else None
        watch = self.camera_motion
        t_m0 = time.perf_counter()
        self._run_deferred_check()   # the last frame's check, if its pipeline left it undone
        t_motion = time.perf_counter() - t_m0
        t_start = time.perf_counter()
        hint = self.hint(frame.index, frame.t_capture) if self._takes_hint else None
        t_hint = time.perf_counter() - t_start
        if hint is None or hint.search_all:
            self._last_full_index = frame.index
        t_avg0 = time.perf_counter()
        image = frame.image
        if self.still_frames is not None:
            reads = getattr(self.detector, "reads", None)      # the detector's search windows, or the whole frame
            region = reads(hint, frame.image.shape) if reads is not None and self._takes_hint else None
            image = self.still_frames.add(frame.image, self._ball_windows, region)
        t_average = time.perf_counter() - t_avg0
        det = self.detector.detect(image, hint) if self._takes_hint else self.detector.detect(image)
        if self.still_frames is not None:
            self._ball_windows = ball_windows(det, getattr(self.detector, "rules", None))
        det = self.memory.fill(det, frame.index, frame.t_capture)
        remembered_det = np.array(["remembered_frames" in f.features for f in det.fiducials], bool)
        pts = det.centres
        known_sigma = self.noise.peek(0.0, 0)
        t0 = time.perf_counter()
        scr = register_screened(self.fiducials_ct, pts, self.camera.K, self.camera.dist, radius_mm=self.radius_mm,
                                method=cfg.method, prior=prior, excluded=tuple(self.excluded),
                                sigma_px=known_sigma.sigma_px if known_sigma.source == "pooled" else None,
                                sigma_dof=known_sigma.dof,
                                min_shift_mm=cfg.moved_min_shift_mm,
                                max_exclusions=2 if cfg.check_moved else 0)
        scr, aside, recheck = self._without_disagreeing(scr, det, pts)
        reg = scr.registration
        if watch is not None:
            t_m0 = time.perf_counter()
            if reg.ok and self._jumped(reg.T_cam_ct):
                # the whole head jumped in the camera since the last trusted pose: a knocked
                # camera looks like this, so the background is checked now, on the frame's path,
                # before the pose can be trusted (due frame or not)
                watch.update(frame.image, pts, force=True)
            elif reg.ok and hasattr(watch, "defer") and watch.next_is_checked():
                watch.defer(frame.image, pts)   # checked after this pose is given out (after_publish)
            else:
                # counts the frame; a due one is checked here when the watch is a plain monitor or
                # the frame gives no pose (its latency does not matter; a knock that lost the
                # balls is then called moved at this frame)
                watch.update(frame.image, pts)
            t_motion += time.perf_counter() - t_m0
        if watch is not None and watch.moved:
            self.memory.reset()
            if self.still_frames is not None:
                self.still_frames.reset()
            return self._invalid(frame.index, frame.t_capture, "camera_moved", watch.last.reason, truth=frame.truth)
        t_gates0 = time.perf_counter()
        t_reg = t_gates0 - t0
        alerts = []
        new_moved = [(m.fiducial_index, round(m.shift_mm, 2)) for m in scr.moved]
        for m in scr.moved:
            self.excluded[m.fiducial_index] = m.shift_mm
            alerts.append(f"fiducial {m.fiducial_index} moved about {m.shift_mm:.1f} mm relative to the others "
                          "since the CT: excluded from registration (check that it is still firmly attached)")

        img_pts = np.full((n, 2), np.nan)
        res = np.full(n, np.nan)
        seen = np.zeros(n, bool)
        remembered = np.zeros(n, bool)      # matched to a ball of an earlier frame (ball_memory)
        ok, reason, code = reg.ok, reg.reason, ("" if reg.ok else "pose_lost")
        sigma = float("nan")
        sigma_src = ""
        tre = float("nan")
        T_pose = reg.T_cam_ct
        n_pooled = 1
        if reg.ok:
            for k, (i, j) in enumerate(reg.pairs):
                img_pts[j] = pts[i]
                res[j] = reg.residuals_px[k] if k < len(reg.residuals_px) else np.nan
                seen[j] = True
                remembered[j] = remembered_det[i]
            for i, j, _px in aside:               # found, set aside for this frame: seen, no residual
                img_pts[j] = pts[i]
                seen[j] = True
                remembered[j] = remembered_det[i]
            matched = [j for _, j in reg.pairs]
            minor = [min(det.fiducials[i].axes_px) for i, _ in reg.pairs]
            if len(reg.pairs) < cfg.min_fiducials:
                ok, reason, code = False, f"only {len(reg.pairs)} fiducials matched (need {cfg.min_fiducials})", \
                    "occlusion"
            elif reg.reprojection_rms_px > cfg.max_rms_px:
                ok, reason, code = False, (f"reprojection RMS {reg.reprojection_rms_px:.2f} px over the "
                                           f"{cfg.max_rms_px:g} px gate"), "pose_lost"
            elif np.nanmax(res) > cfg.max_residual_px:
                j = int(np.nanargmax(res))
                ok, reason, code = False, (f"fiducial {j} residual {res[j]:.2f} px over the "
                                           f"{cfg.max_residual_px:g} px gate"), "pose_lost"
            else:
                why = physical_problem(reg.T_cam_ct, self.fiducials_ct, self.radius_mm, float(self.camera.K[0, 0]),
                                       matched, np.array(minor),
                                       PhysicalLimits(cfg.min_distance_mm, cfg.max_distance_mm))
                if why:
                    ok, reason, code = False, why, "pose_implausible"
                else:
                    why = weak_geometry(self.fiducials_ct, matched, cfg.min_fiducials)
                    if why:
                        ok, reason, code = False, why, "weak_geometry"
            if code not in ("pose_implausible",):
                # the fit passed the residual gates: its residuals are a noise sample
                rss, dof = scr.noise_rss_px2, scr.noise_dof   # the fit's residuals (suspect ball trimmed)
                ne = self.noise.update(rss, dof) if code in ("", "weak_geometry") else self.noise.peek(rss, dof)
                sigma, sigma_src = ne.sigma_px, ne.source
                if self.centre_bias is not None:
                    usable = code in ("", "weak_geometry")
                    T_pose, tre, sigma, sigma_src, ok, code, reason, n_pooled = self.pooled.judge(
                        frame.index, reg, pts, det, ne.sigma_px, new_moved, usable, ok, code, reason, self.target_ct)
                elif self.target_ct is not None:
                    tre, ok, code, reason = self.trust.judge(reg, det, ne, self.target_ct, recheck, ok, code, reason,
                                                             int(remembered.sum()))
            else:
                self.pool.reset()
        else:
            self.pool.reset()
            if len(pts) < cfg.min_fiducials:
                reason = f"{len(pts)} fiducials detected (need {cfg.min_fiducials}): {reason}"
                code = "occlusion"
            # best-effort status from the last valid pose
            own = pts[~remembered_det]      # what this frame found (not the remembered balls)
            if self._last_T is not None and len(own):
                proj = self.camera.project(apply_transform(self._last_T, self.fiducials_ct))
                d = np.linalg.norm(proj[:, None] - own[None], axis=2)
                for j in range(n):
                    if j in self.excluded:
                        continue
                    i = int(np.argmin(d[j]))
                    if d[j, i] <= cfg.status_gate_px:
                        seen[j] = True
                        img_pts[j] = own[i]
        status, changes = self.states.after_frame(seen, remembered, self.excluded, aside, frame.index)
        alerts += changes
        if not ok and (self._last_ok or self._last_ok is None or code != self._last_code):
            alerts.append(f"no valid pose: {reason}")
        self._last_ok = ok
        self._last_code = code if not ok else ""

        T = T_pose if ok else None
        stages = {"hint": t_hint, "average": t_average, "detect": det.time_s, "register": scr.register_s, "screen": scr.screen_s,
                  "gates": time.perf_counter() - t_gates0, "motion": t_motion}
        stages.update({f"detect.{k}": v for k, v in getattr(det, "stages_s", {}).items()})
        if ok:
            self._last_T = T_pose
            self._last_T_time = frame.t_capture
            self._last_T_index = frame.index
        return PoseEstimate(
            ok=ok, reason="" if ok else reason, frame_index=frame.index, t_capture=frame.t_capture,
            t_published=time.monotonic(), T_cam_ct=T, status=status, image_points_px=img_pts, residuals_px=res,
            fre_mm=float(reg.fre_mm) if ok else float("nan"),
            reprojection_rms_px=float(reg.reprojection_rms_px) if reg.ok else float("nan"),
            predicted_tre_mm=tre, n_detected=int((~remembered_det).sum()), n_matched=int(seen.sum()) if reg.ok else 0,
            alerts=alerts, used_prior=bool(reg.used_prior), detect_s=det.time_s, register_s=t_reg,
            truth=frame.truth, code="" if ok else code, sigma_px=sigma, sigma_source=sigma_src,
            moved=new_moved, excluded=sorted(self.excluded), stages_s=stages,
            pooled_frames=n_pooled if ok else 0, remembered=[int(j) for j in np.flatnonzero(remembered)],
            averaged_frames=min(self.still_frames.n, self.still_frames.max_frames)
            if self.still_frames is not None and self.still_frames.giving else 1,
            set_aside=[(int(j), round(float(px), 2)) for _, j, px in aside])

    def _without_disagreeing(self, scr, det, pts: np.ndarray):
        """(the screened registration to judge, [(detection index, fiducial, px)] of the balls
        set aside for this frame, whether the trust model must still test the fit's balls: the
        test did not run, named balls it could not set aside, or set some aside: a second ball
        off, masked by the first, is judged in the fit without it). A ball the others put beyond its cover
        (``disagreement_quantile``: :meth:`.frame_trust.FrameTrust.disagreeing`) is left out of this frame's fit when at
        least :data:`~monotracker.registration.disagreement.MIN_BALLS` balls remain and the fit
        without it succeeds: the pose comes from the balls that agree (the re-fit starts from
        this frame's pose); otherwise ``scr`` as it is (the trust model then covers the ball by
        its disagreement, :meth:`.frame_trust.FrameTrust.covariances`). Not in a frame that found a fiducial
        moved (that frame's fit already left it out)."""
        import dataclasses

        from monotracker.registration.consistency import register_screened
        from monotracker.registration.disagreement import MIN_BALLS

        cfg = self.config
        reg = scr.registration
        if scr.moved or not reg.ok or not (cfg.disagreement_quantile > 0):
            return scr, [], True
        ne = self.noise.peek(scr.noise_rss_px2, scr.noise_dof) if scr.noise_dof > 0 else self.noise.peek(0.0, 0)
        found = self.trust.disagreeing(reg, det, ne.sigma_px)
        if found is None or not found:
            return scr, [], found is None
        take = found[:len(reg.pairs) - MIN_BALLS]
        again = register_screened(self.fiducials_ct, pts, self.camera.K, self.camera.dist, radius_mm=self.radius_mm,
                                  method=cfg.method, prior=reg.T_cam_ct,
                                  excluded=tuple(self.excluded) + tuple(j for j, _ in take), max_exclusions=0)
        kept = again.registration
        if not kept.ok or len(kept.pairs) < len(reg.pairs) - len(take):
            return scr, [], True
        det_of = {j: i for i, j in reg.pairs}
        again = dataclasses.replace(again, register_s=scr.register_s + again.register_s,
                                    screen_s=scr.screen_s + again.screen_s)
        return again, [(det_of[j], j, px) for j, px in take], True     # the new fit is tested again

    def hint(self, frame_index: int, t_capture: float):
        """The :class:`~.detection.DetectionHint` for frame ``frame_index`` (captured at
        ``t_capture``, monotonic s): the registration and watched balls' ellipses predicted from
        the last trusted pose (``search_all`` set when a full-frame search is due,
        :attr:`TrackerConfig.full_search_every`), or None (a cold full-frame search) when that pose
        is older than :attr:`TrackerConfig.hint_max_age_frames` frames or ``prior_max_age_s``."""
        from .detection import DetectionHint

        cfg = self.config
        age = frame_index - self._last_T_index
        if (self._last_T is None or cfg.hint_max_age_frames <= 0 or not 1 <= age <= cfg.hint_max_age_frames
                or t_capture - self._last_T_time > cfg.prior_max_age_s):
            return None
        search_all = cfg.full_search_every > 0 and frame_index - self._last_full_index >= cfg.full_search_every
        X = np.vstack([self.fiducials_ct, self.watch_ct])
        return DetectionHint.from_pose(self.camera, self._last_T, X, self.radius_mm, self._last_T_index, age,
                                       search_all=search_all, ellipses=self._hint_ellipses)

    def _invalid(self, frame_index: int, t_capture: float, code: str, reason: str, camera: str = "ok",
                 truth=None) -> PoseEstimate:
        """An invalid estimate that saw nothing (camera fault, unusable frame); the alert is
        raised once per episode (per code); the next good frame starts from a full search."""
        n = len(self.fiducials_ct)
        status = self.states.after_invalid(self.excluded)
        repeat = self._last_ok is False and self._last_code == code
        self.pool.reset()
        self._last_T_time = -np.inf
        self._last_T_index = -10
        self._last_ok = False
        self._last_code = code
        return PoseEstimate(ok=False, reason=reason, frame_index=frame_index, t_capture=t_capture,
                            t_published=time.monotonic(), status=status, image_points_px=np.full((n, 2), np.nan),
                            residuals_px=np.full(n, np.nan), alerts=[] if repeat else [reason], camera=camera,
                            code=code, truth=truth, excluded=sorted(self.excluded))

    def camera_fault(self, frame_index: int, t_capture: float, camera: str, reason: str) -> PoseEstimate:
        """An invalid estimate for a camera fault (``camera``: frozen, late, stalled,
        disconnected, ended, unreadable; its alert code from ``CAMERA_CODES``); the next good
        frame starts from a full search, except after ``late`` (a frame that is only late: the
        tracking state stays, the next frame continues from it)."""
        if camera == "late":
            n = len(self.fiducials_ct)
            return PoseEstimate(ok=False, reason=reason, frame_index=frame_index, t_capture=t_capture,
                                t_published=time.monotonic(), status=[UNKNOWN] * n,
                                image_points_px=np.full((n, 2), np.nan), residuals_px=np.full(n, np.nan),
                                alerts=[reason], camera=camera, code=CAMERA_CODES["late"],
                                excluded=sorted(self.excluded))
        if self.still_frames is not None:
            self.still_frames.reset()     # what comes after a camera fault is not the same view
        est = self._invalid(frame_index, t_capture, CAMERA_CODES.get(camera, "camera_freeze"), reason, camera)
        est.alerts = [reason]
        return est


def _takes_hint(detector) -> bool:
    """True when ``detector.detect`` accepts a second argument (the hint)."""
    import inspect

    try:
        params = list(inspect.signature(detector.detect).parameters.values())
    except (TypeError, ValueError):
        return False
    return len(params) >= 2 or any(p.kind == p.VAR_POSITIONAL for p in params)
