"""The trust model of a still head's pooled frames (``TrackerConfig.centre_bias`` set; opt-in):
the pose refitted to each fiducial's mean centre over the frames of a still head, and its
predicted error at the target from the pool's scatter and the centre-bias prior
(:class:`PooledTrust`). The per-frame model, the default, is :mod:`.frame_trust`."""

from __future__ import annotations

import numpy as np

from monotracker.registration.quantiles import chi2_ppf as chi2_quantile

from .tracker_config import TrackerConfig, tail_problem


class PooledTrust:
    """Pools a still head's matched centres and judges the pose of their means.

    Args:
        config: the gates (:class:`~.tracker_config.TrackerConfig`).
        camera: the calibrated :class:`~.camera_model.CameraModel`.
        fiducials_ct: (n, 3) float, CT LPS mm: the fiducial centres.
        radius_mm: ball radius, mm.
        centre_bias: the detector's measured centre bias (:mod:`.centre_bias`).
        pool: the tracker's :class:`~.still_pool.StillPool` (the tracker restarts it when the
            head moves, a frame is unusable or a camera fault comes).
    """

    def __init__(self, config: TrackerConfig, camera, fiducials_ct: np.ndarray, radius_mm: float, centre_bias, pool):
        self.config = config
        self.camera = camera
        self.fiducials_ct = fiducials_ct
        self.radius_mm = float(radius_mm)
        self.centre_bias = centre_bias
        self.pool = pool

    def judge(self, frame_index: int, reg, pts: np.ndarray, det, frame_sigma_px: float, new_moved: list,
              usable: bool, ok: bool, code: str, reason: str, target_ct: np.ndarray | None):
        """The pose of the still head's pooled frames and its trust (``TrackerConfig.centre_bias``):
        ``target_ct``: (3,) CT LPS mm or None (no predicted error then); returns (T_cam_ct,
        predicted TRE mm, sigma px, sigma source, ok, code, reason, frames pooled).

        The frame's matched centres join the :class:`~.still_pool.StillPool` (a head that moved
        restarts it); the pose is refitted to each fiducial's mean centre; the per-ball error of
        those means comes from the refit's residuals with the bias prior
        (:func:`~monotracker.registration.noise.pooled_sigma`), the frame-to-frame noise from the
        pool's scatter; a shift common to all balls (which no residual shows) is added as the
        prior says (:func:`~monotracker.registration.report.common_shift_covariance`), and so is
        a bias that changes linearly across the layout
        (:func:`~monotracker.registration.report.layout_gradient_covariance`). The gates
        use the upper bound of the per-ball error (``noise_bound_confidence``): RMS at the target
        <= ``max_predicted_tre_mm``, P(> ``wrong_mm``) <= ``max_wrong_probability``, P(>
        ``right_mm``) <= ``max_not_right_probability``."""
        from monotracker.registration.noise import pooled_sigma
        from monotracker.registration.pnp import refine_pose
        from monotracker.registration.projection import undistort_to_normalised
        from monotracker.registration.report import (common_shift_covariance, layout_gradient_covariance, predicted_tre,
                                                     target_covariance)

        cfg, bias = self.config, self.centre_bias
        K = self.camera.K
        fxy = np.array([K[0, 0], K[1, 1]])
        if new_moved or not usable:
            self.pool.reset()        # a fiducial was just excluded, or the frame is unusable
        if usable:
            # the frame that found a fiducial moved starts the new pool: its fit (``reg``) has
            # that fiducial left out already, so it is judged like any other frame (before, it
            # was given out trusted with no predicted error at all: 1.19 mm off in
            # tests/vision/test_pose_trust.py's 0.6 px stream)
            idx = np.array([i for i, _ in reg.pairs], int)
            fids = [j for _, j in reg.pairs]
            xn = undistort_to_normalised(pts[idx], K, self.camera.dist)
            self.pool.add(frame_index, fids, xn, fxy, frame_sigma_px)
        st = self.pool.stats()
        if st is None or len(st.fiducials) < cfg.min_fiducials:
            if ok and target_ct is not None:
                # never trusted without a predicted error at the target
                ok, code = False, "tre_limit"
                reason = f"no predicted error at the target: fewer than {cfg.min_fiducials} fiducials pooled"
            return reg.T_cam_ct, float("nan"), frame_sigma_px, "frame", ok, code, reason, 1
        X = self.fiducials_ct[st.fiducials]
        fit = refine_pose(reg.T_cam_ct, X, st.means, fxy, self.radius_mm)
        k = len(st.fiducials)
        dof = 2 * k - 6
        rss = float(np.sum(fit.residuals**2))
        radius_px = float(np.median([min(f.axes_px) for f in det.fiducials])) if det.fiducials else 0.0
        if st.noise_dof >= 4:
            noise = st.noise_px * float(np.sqrt(st.noise_dof / chi2_quantile(1.0 - cfg.noise_bound_confidence,
                                                                              st.noise_dof)))
        else:
            noise = bias.noise_prior_px
        n_h = float(k / np.sum(1.0 / st.counts))
        ps = pooled_sigma(rss, dof, noise, n_h, bias.ball_sigma(radius_px), bias.prior_dof,
                          cfg.noise_bound_confidence)
        H_inv = np.linalg.pinv(fit.J.T @ fit.J)
        A = H_inv @ fit.J.T
        common = common_shift_covariance(fit.J, bias.common_sigma(radius_px), A)
        if bias.gradient_sigma(radius_px) > 0:
            common = common + layout_gradient_covariance(fit.J, st.means * fxy, bias.gradient_sigma(radius_px), A)
        cov_est = ps.sigma_px**2 * H_inv + common
        cov_hi = ps.upper_px**2 * H_inv + common
        src = f"{st.frames} frame{'s' if st.frames > 1 else ''}, {ps.source}"
        if target_ct is None:
            return fit.T, float("nan"), ps.sigma_px, src, ok, code, reason, st.frames
        tre = float(predicted_tre(fit.T, cov_est, target_ct))
        tre_hi = float(predicted_tre(fit.T, cov_hi, target_ct))
        if ok:
            cov3 = target_covariance(fit.T, cov_hi, target_ct)
            why = ""
            if not tre_hi <= cfg.max_predicted_tre_mm:
                why = f"up to {tre_hi:.2f} mm at {100 * cfg.noise_bound_confidence:.0f} %: over the " \
                      f"{cfg.max_predicted_tre_mm:g} mm limit"
            else:
                why = tail_problem(cov3, cfg)
            if why:
                ok, code = False, "tre_limit"
                reason = (f"predicted error at the target {tre:.2f} mm, {why} (centre error {ps.sigma_px:.2f} px per "
                          f"ball, {k} fiducials, {src})")
        return fit.T, tre, ps.sigma_px, src, ok, code, reason, st.frames
