"""The per-frame trust model of one fit (issue 28): how far the pose of one frame's registration
may be off at the planned target, and whether that passes the gates (:class:`FrameTrust`).

Each matched ball's centre error per coordinate (px) counts as at least the image noise, and as
its edge fit's residual RMS x ``TrackerConfig.edge_bias_per_rms`` (widened with few or glossy
balls: :func:`.tracker_config.few_ball_factor`); a shift common to all balls
(``edge_common_per_rms`` x their median edge RMS) is added, and where contact shadows lie beside
the balls the shading check (:mod:`.shading_check`) raises the covariance along the pose change
the balls' second centre readings give. A ball the others put beyond its cover (a linearised
leave-one-out, :mod:`monotracker.registration.disagreement`) is named here; the tracker sets it
aside or this model covers it by its disagreement. The pose covariance (6x6: rotation vector rad,
translation mm) goes to the target (mm): RMS <= ``max_predicted_tre_mm`` and the tail gates
(:func:`.tracker_config.tail_problem`) with the noise's upper bound.

A detector without an edge fit (no ``edge_rms_px``) leaves the residuals' noise alone to decide.
The trust model of a still head's pooled frames is :mod:`.pooled_trust`.
"""

from __future__ import annotations

import numpy as np

from . import ball_gloss, lens_range, shading_check
from .tracker_config import TrackerConfig, few_ball_factor, tail_problem

#: the note each frame leaves in the ball memory: the share of its matched balls with a contact
#: shadow beside them (:func:`.shading_check.shadowed_share`), read by the next frames of a still
#: head (:meth:`.ball_memory.StillBallMemory.still_notes`)
SHADOWED_NOTE = "shadowed_share"
#: the note of each frame's highlight reading (:func:`.ball_gloss.frame_highlight`), read the same way
HIGHLIGHT_NOTE = "highlight_ratio"


def fiducials_used(n: int, remembered: int) -> str:
    """'7 fiducials' or '7 fiducials, 2 of them from the last frames' (a refusal's reason)."""
    return f"{n} fiducials" + (f", {remembered} of them from the last frames" if remembered else "")


def ball_features(reg, det) -> tuple[list, np.ndarray, np.ndarray]:
    """The matched balls' detection features (``reg.pairs`` order), their edge fits' RMS (px; NaN
    for a detector without an edge fit) and whether the learned refiner moved each centre."""
    feats = [det.fiducials[i].features for i, _ in reg.pairs]
    rms = np.array([float(f.get("edge_rms_px", np.nan)) for f in feats])
    refined = np.array(["edge_centre_px" in f for f in feats], bool)
    return feats, rms, refined


class FrameTrust:
    """The trust model of one frame's fit.

    Args:
        config: the gates and cover factors (:class:`~.tracker_config.TrackerConfig`).
        camera: the calibrated :class:`~.camera_model.CameraModel` (K, distortion).
        fiducials_ct: (n, 3) float, CT LPS mm: the fiducial centres.
        radius_mm: ball radius, mm.
        memory: the tracker's :class:`~.ball_memory.StillBallMemory`: this model leaves each
            frame's shading and highlight notes there and reads the last frames' of a still head.
        outlines: the tracker's :class:`~.sphere_outline.SphereEllipseCache` (the hint's
            predicted outlines: the size excess reads the spheres' outlines at the fit's pose).

    The fit's rows and the balls' covers are read once per frame (kept for the registration they
    were read for): the test before the gates (:meth:`disagreeing`) and the gates
    (:meth:`judge`) share them.
    """

    def __init__(self, config: TrackerConfig, camera, fiducials_ct: np.ndarray, radius_mm: float, memory,
                 outlines):
        self.config = config
        self.camera = camera
        self.fiducials_ct = fiducials_ct
        self.radius_mm = float(radius_mm)
        self.memory = memory
        self.outlines = outlines
        #: the camera's lens images the balls under the judged size (:mod:`.lens_range`; a radius
        #: that is no ball's is left to the tracker's own checks)
        self.short_lens = lens_range.is_short(camera, radius_mm)
        self._rows = None                # (registration, its rows): fit_rows' last
        self._covers = None              # (registration, its covers): centre_covers' last

    def band_floor_px(self) -> float:
        """The shading check's floor (px) for a banded ball's second reading: the config's, or its
        short-lens floor where the lens is short (the larger)."""
        cfg = self.config
        return max(float(cfg.shading_check_band_floor_px), float(cfg.short_lens_band_floor_px) if self.short_lens else 0.0)

    def judge(self, reg, det, noise, target_ct: np.ndarray, recheck: bool, ok: bool, code: str, reason: str,
              n_remembered: int) -> tuple[float, bool, str, str]:
        """The trust verdict of the fit ``reg`` (its matched detections in ``det``) at the target
        ``target_ct`` ((3,) CT LPS mm), with the online noise estimate ``noise``
        (:class:`~monotracker.registration.noise.NoiseEstimate`; the gates use its upper bound at
        ``noise_bound_confidence``: a sigma from few dof may be low by chance). ``recheck``: the
        balls' disagreement must still be tested (the tracker did not, or set balls aside).
        ``ok`` / ``code`` / ``reason``: the verdict of the gates before this one (kept when not
        ok); ``n_remembered``: matched balls taken from the last frames (named in a refusal).
        Returns (predicted RMS error at the target mm, ok, code, reason): refused as
        ``tre_limit`` when the RMS bound or a tail gate fails."""
        from monotracker.registration.report import predicted_tre, target_covariance

        cfg = self.config
        sigma = noise.sigma_px
        upper = noise.upper(cfg.noise_bound_confidence)
        upper = upper if np.isfinite(upper) else sigma
        covs = self.covariances(reg, det, sigma, upper, target_ct, recheck)
        shading = ""
        if covs is None:
            tre = float(reg.predicted_tre_mm(target_ct, sigma_px=sigma))
            tre_hi = tre * upper / sigma if sigma > 0 else tre
        else:
            cov_est, cov_hi, edge_px, check_mm, glossy_cover, disagreeing = covs
            tre = float(predicted_tre(reg.T_cam_ct, cov_est, target_ct))
            tre_hi = float(predicted_tre(reg.T_cam_ct, cov_hi, target_ct))
            shading = f", edge spread {edge_px:.2f} px"
            if check_mm is not None:
                shading += f", the shading-corrected centres move the target {check_mm:.2f} mm"
            if glossy_cover:
                shading += ", glossy balls beside contact shadows: each ball's cover widened"
            for j, px in disagreeing:
                shading += (f", fiducial {j} lies {px:.1f} px from where the others put it (partly "
                            "hidden or off?): its cover widened to that")
        used = fiducials_used(len(reg.pairs), n_remembered)
        if ok and not (tre_hi <= cfg.max_predicted_tre_mm):
            ok, code = False, "tre_limit"
            bound = (f"; up to {tre_hi:.2f} mm at {100 * cfg.noise_bound_confidence:.0f} % with {noise.dof} dof"
                     if tre_hi > tre + 0.005 else "")
            reason = (f"predicted error at the target {tre:.2f} mm{bound}: over the "
                      f"{cfg.max_predicted_tre_mm:g} mm limit (image noise {sigma:.2f} px{shading}, {used})")
        elif ok and reg.pose_covariance is not None and reg.sigma_px > 0:
            if covs is None:
                cov3 = target_covariance(reg.T_cam_ct, reg.pose_covariance, target_ct)
                cov3 = cov3 * (upper / reg.sigma_px) ** 2
            else:
                cov3 = target_covariance(reg.T_cam_ct, covs[1], target_ct)
            why = tail_problem(cov3, cfg)
            if why:
                ok, code = False, "tre_limit"
                reason = (f"predicted error at the target {tre:.2f} mm, but {why} (image noise "
                          f"{sigma:.2f} px{shading}, {used})")
        return tre, ok, code, reason

    def disagreeing(self, reg, det, sigma_px: float) -> list | None:
        """[(fiducial, px)] of the matched balls whose leave-one-out disagreement with the others
        is beyond ``disagreement_quantile`` of their covers (:meth:`centre_covers`, noise
        ``sigma_px``), the worst first; None where the test does not run here (a detector
        without an edge spread, at most
        :data:`~monotracker.registration.disagreement.MIN_BALLS` balls: none could be set aside)."""
        from monotracker.registration.disagreement import MIN_BALLS, disagreement_cover

        feats, rms, refined = ball_features(reg, det)
        if len(rms) <= MIN_BALLS or not np.all(np.isfinite(rms)) or not (sigma_px > 0):
            return None
        fids, r, J = self.fit_rows(reg, det)
        cover = self.centre_covers(reg, feats, rms, refined)[0]
        _floor, found = disagreement_cover(r, J, np.maximum(sigma_px**2, np.repeat(cover**2, 2)),
                                           self.config.disagreement_quantile)
        return [(fids[i], px) for i, px in found]

    def covariances(self, reg, det, sigma_px: float, upper_px: float, target_ct: np.ndarray | None,
                    disagreement: bool = True):
        """The pose covariances (6, 6; rotation vector rad, translation mm) of one frame's fit with
        the balls' shading error covered (``TrackerConfig.edge_bias_per_rms``,
        ``edge_common_per_rms``): (with the noise estimate ``sigma_px``, with its upper bound
        ``upper_px``, the median edge RMS px, the shading check's target move mm or None where it
        does not apply, whether the glossy frames' wider few-ball cover applied, [(fiducial,
        px)] of the balls covered by their disagreement with the others). Per matched
        ball the centre error per coordinate is max(noise, ``edge_bias_per_rms`` x its edge RMS;
        with few balls x ``few_balls_cover``, or the glossy frames' pair, :mod:`.ball_gloss`;
        where the others' leave-one-out disagreement with it is beyond that,
        ``disagreement_quantile``, that disagreement; not tested again where ``disagreement`` is
        False: the tracker tested this fit) (a weighted least-squares fit's
        covariance ``H^-1 J^T V J H^-1``), plus a shift common to all balls of
        ``edge_common_per_rms`` x their median edge RMS; where the shading check applies
        (``shading_check_factor``, :mod:`.shading_check`; with a target ``target_ct``, (3,) CT
        LPS mm) raised along the pose change the balls' second centre readings give. None when
        off or when a matched ball has no edge RMS (a detector without an edge fit): the
        residuals' noise alone decides."""
        cfg = self.config
        if cfg.edge_bias_per_rms <= 0 and cfg.edge_common_per_rms <= 0:
            return None
        feats, rms, refined = ball_features(reg, det)
        if not len(rms) or not np.all(np.isfinite(rms)) or not (sigma_px > 0 and np.isfinite(upper_px)):
            return None
        from monotracker.registration.disagreement import disagreement_cover
        from monotracker.registration.report import common_shift_covariance, layout_gradient_covariance

        T = reg.T_cam_ct
        fids, r, J = self.fit_rows(reg, det)
        k = len(fids)
        A = np.linalg.pinv(J.T @ J) @ J.T                      # (6, 2k): image errors -> pose error
        cover, spread, excess, glossy = self.centre_covers(reg, feats, rms, refined)
        self.memory.note(HIGHLIGHT_NOTE, ball_gloss.frame_highlight(feats))
        common_factor = max(cfg.refined_common_per_rms if refined.any() else 0.0,
                            cfg.edge_common_per_rms if not refined.all() else 0.0)
        shade = np.repeat(cover ** 2, 2)
        if disagreement:
            # a ball the others disagree with beyond its cover (and not set aside) is covered by
            # that disagreement
            floor, found = disagreement_cover(r, J, np.maximum(sigma_px**2, shade), cfg.disagreement_quantile)
            shade = np.maximum(shade, floor)
        else:
            found = []
        common = common_shift_covariance(J, common_factor * float(np.median(spread)), A)  # shared by all balls
        if cfg.edge_gradient_per_rms > 0:
            pts = np.array([det.fiducials[i].centre_px for i, _ in reg.pairs], float)
            common = common + layout_gradient_covariance(J, pts, cfg.edge_gradient_per_rms * float(np.median(rms)), A)
        disagree, check_mm = None, None
        if cfg.shading_check_factor > 0 and target_ct is not None:
            # a still head's contact shadows stay: the shares of its last frames count too
            still = tuple(self.memory.still_notes(SHADOWED_NOTE)) if cfg.shading_check_still_frames else ()
            if shading_check.applies(feats, cfg.shading_check_share, still, cfg.shading_check_small_radius_px):
                read = None
                if cfg.shading_check_reading == "excess":
                    # the outlines' excess over the spheres at this pose (px; only where the check applies)
                    read = excess if excess is not None else self.size_excess(T, fids, feats)
                disagree = shading_check.pose_disagreement(A, feats, read, band_min_px=self.band_floor_px())
            elif shading_check.unseen_push_applies(feats, cfg.shading_check_unseen_push_px, still,
                                                   cfg.shading_check_push_min_share):
                # too few shadows seen for the check: each shaded ball's push taken as at least the floor
                disagree = shading_check.pose_disagreement(A, feats, min_px=cfg.shading_check_unseen_push_px,
                                                           band_min_px=self.band_floor_px())
            if disagree is not None:
                check_mm = shading_check.target_move_mm(disagree, T, target_ct)
            self.memory.note(SHADOWED_NOTE, shading_check.shadowed_share(feats))

        def cov(noise_px: float) -> np.ndarray:
            c6 = (A * np.maximum(noise_px**2, shade)) @ A.T + common
            if disagree is None:
                return c6
            return shading_check.raised_covariance(c6, disagree, T, target_ct, cfg.shading_check_factor)

        return (cov(sigma_px), cov(upper_px), float(np.median(rms)), check_mm, bool(glossy and k <= cfg.glossy_few_balls),
                [(fids[i], px) for i, px in found])

    def fit_rows(self, reg, det) -> tuple[list, np.ndarray, np.ndarray]:
        """(matched fiducial indices, residuals r (2k,) px, Jacobian J (2k, 6) px per (rad, mm))
        of the fit ``reg`` at its pose, from the matched detections' centres (rows u, v per
        ball, in ``reg.pairs`` order)."""
        from monotracker.registration import pnp_kernels
        from monotracker.registration.projection import undistort_to_normalised

        cached = self._rows
        if cached is not None and cached[0] is reg:
            return cached[1]                 # this frame's fit, read once by both of its tests
        K, T = self.camera.K, reg.T_cam_ct
        fids = [j for _, j in reg.pairs]
        X = np.ascontiguousarray(self.fiducials_ct[fids], dtype=float)
        k = len(X)
        obs = undistort_to_normalised(np.array([det.fiducials[i].centre_px for i, _ in reg.pairs], float).reshape(-1, 2),
                                      K, self.camera.dist)
        r, J = np.empty(2 * k), np.empty((2 * k, 6))
        pnp_kernels.residuals_and_jacobian(np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), X,
                                           np.ascontiguousarray(obs, dtype=float), float(K[0, 0]), float(K[1, 1]),
                                           float(self.radius_mm or 0.0), np.empty(0), r, J)
        self._rows = (reg, (fids, r, J))
        return fids, r, J

    def centre_covers(self, reg, feats: list, rms: np.ndarray, refined: np.ndarray):
        """Each matched ball's centre cover per coordinate (px; its edge RMS x its factor, with few
        balls or glossy frames widened, :func:`~.tracker_config.few_ball_factor`; or its size
        excess where that is covered), the spread behind the common shift (px), the size excess
        (px) or None, and whether the frame's balls read as glossy. Reads the ball memory's
        notes, writes none."""
        cached = self._covers
        if cached is not None and cached[0] is reg:
            return cached[1]                 # this frame's fit, read once by both of its tests
        cfg = self.config
        fids = [j for _, j in reg.pairs]
        per_ball = np.where(refined, cfg.refined_bias_per_rms, cfg.edge_bias_per_rms)
        glossy = ball_gloss.wider_cover(feats, cfg.glossy_highlight_ratio,
                                        cfg.shading_check_share if cfg.glossy_needs_shadow else None,
                                        tuple(self.memory.still_notes(HIGHLIGHT_NOTE)),
                                        tuple(self.memory.still_notes(SHADOWED_NOTE)), cfg.ball_finish)
        per_ball = per_ball * few_ball_factor(cfg, len(fids), glossy)
        cover = per_ball * rms
        spread = rms
        excess = self.size_excess(reg.T_cam_ct, fids, feats) if cfg.edge_size_per_excess > 0 else None
        if excess is not None:
            # a centre the refiner moved has its own measured factors (the excess is the
            # edge fit's, whose bias the refiner corrects)
            size_cover = np.where(refined, 0.0, cfg.edge_size_per_excess * np.abs(excess))
            cover = np.maximum(cover, size_cover)
            spread = np.maximum(rms, size_cover)
        self._covers = (reg, (cover, spread, excess, glossy))
        return cover, spread, excess, glossy

    def size_excess(self, T_cam_ct: np.ndarray, fiducials: list, feats: list):
        """Per matched ball (``fiducials`` their indices, ``feats`` their detections' features),
        its fitted outline's minor semi-axis (``features["edge_minor_px"]``) minus that of the
        sphere of ``radius_mm`` at the pose ``T_cam_ct`` (px; > 0: the outline is too large);
        None when a ball has no fitted size or its outline does not project. The outlines of all
        fiducials come from the hint's cache (:class:`~.sphere_outline.SphereEllipseCache`: this
        pose is near the hint's, so they are mostly reused, moved and scaled)."""
        minor = np.array([float(f.get("edge_minor_px", np.nan)) for f in feats])
        if not (self.radius_mm > 0) or not np.all(np.isfinite(minor)):
            return None
        C = self.fiducials_ct @ T_cam_ct[:3, :3].T + T_cam_ct[:3, 3]
        _cen, axes, _ang, ok = self.outlines(self.camera, C, self.radius_mm)
        if not np.all(ok[fiducials]):
            return None
        return minor - axes[fiducials, 1]
