"""The :class:`Registration` result."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .report import predicted_tre


@dataclass
class Registration:
    """Outcome of :func:`monotracker.registration.register`.

    ``T_cam_ct`` (4x4, mm) maps CT points into the OpenCV camera frame; it is ``None`` when
    ``ok`` is False (``reason`` says why; a fit that was refused, e.g. as ambiguous, is kept in
    ``stats["rejected_T_cam_ct"]`` / ``stats["rejected_pairs"]`` for diagnosis only).

    Attributes:
        ok: True when the pose passed every acceptance gate; False means "do not use".
        reason: one line saying why ``ok`` is False ("" when ok).
        method: the method that ran: "robust", "paper" or "naive".
        T_cam_ct: (4, 4) float64, CT LPS mm -> OpenCV camera mm (x right, y down, z forward);
            None when not ok.
        pairs: k tuples (image index, fiducial index): which image point is which CT fiducial
            (indices into the ``image_points`` and ``fiducials_ct`` given); [] when not ok.
        fre_mm: monocular fiducial registration error, mm: RMS distance from each matched
            fiducial (moved by ``T_cam_ct``) to its image point's viewing ray (see :mod:`.report`).
        reprojection_rms_px: RMS reprojection error over the pairs, equivalent pinhole px.
        residuals_px: (k,) reprojection error magnitude per pair, px, in the order of ``pairs``.
        residual_vectors_px: (k, 2) observed minus predicted image position per pair, px.
        unmatched_image_indices: image points explained by no fiducial (stray blobs), sorted.
        unmatched_fiducial_indices: fiducials not seen in the image (occluded, out of view), sorted.
        sigma_px: per-coordinate image noise estimated from the residuals, px (floored at
            ``report.SIGMA_FLOOR_PX``; ``sigma_dof`` degrees of freedom).
        pose_covariance: (6, 6) covariance of the pose: rotation vector (rad) then translation
            (mm), camera frame; None when not ok.
        timing: seconds per stage (``undistort_s``, ``prior_s``, ``search_s``; ``total_s`` always).
        stats: search diagnostics (counts, ``prior_rejected``, ``ambiguous_pairs``,
            ``rejected_T_cam_ct``, ``rejected_pairs``); for logs, not a stable API.
        used_prior: True when the ``prior`` fast path produced this pose (no full search ran).
        sigma_dof: residual degrees of freedom behind ``sigma_px`` (2k - 6 for k pairs).
    """

    ok: bool
    reason: str
    method: str
    T_cam_ct: np.ndarray | None = None
    pairs: list = field(default_factory=list)
    fre_mm: float = float("nan")
    reprojection_rms_px: float = float("nan")
    residuals_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    residual_vectors_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    unmatched_image_indices: list = field(default_factory=list)
    unmatched_fiducial_indices: list = field(default_factory=list)
    sigma_px: float = float("nan")
    pose_covariance: np.ndarray | None = None   # (6, 6): rotation vector (rad) then translation (mm), camera frame
    timing: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
    used_prior: bool = False
    #: residual degrees of freedom behind ``sigma_px`` (2k - 6 for k pairs)
    sigma_dof: int = 0

    def predicted_tre_mm(self, target_ct: np.ndarray, sigma_px: float | None = None) -> float | np.ndarray:
        """Predicted RMS 3D error (mm) at target(s) from the pose covariance.

        Args:
            target_ct: (3,) or (t, 3) float, CT LPS mm.
            sigma_px: use this image noise (px, e.g. the pose stream's pooled estimate) instead
                of this fit's own ``sigma_px``; None keeps the fit's own.

        Returns:
            float for one target, (t,) array for several, mm; NaN when not ok.
        """
        if not self.ok or self.pose_covariance is None:
            return float("nan") if np.ndim(target_ct) == 1 else np.full(len(target_ct), np.nan)
        cov = self.pose_covariance
        if sigma_px is not None and np.isfinite(sigma_px) and self.sigma_px > 0:
            cov = cov * (float(sigma_px) / self.sigma_px) ** 2
        return predicted_tre(self.T_cam_ct, cov, target_ct)

    def to_dict(self) -> dict:
        """JSON-ready summary (lists and floats; no numpy) for logs and persistence."""
        def f(x):
            return None if x is None or not np.isfinite(x) else float(x)

        return {
            "ok": self.ok, "reason": self.reason, "method": self.method,
            "T_cam_ct": None if self.T_cam_ct is None else np.asarray(self.T_cam_ct).tolist(),
            "pairs": [list(p) for p in self.pairs], "fre_mm": f(self.fre_mm),
            "reprojection_rms_px": f(self.reprojection_rms_px),
            "residuals_px": np.asarray(self.residuals_px, float).tolist(),
            "unmatched_image_indices": list(self.unmatched_image_indices),
            "unmatched_fiducial_indices": list(self.unmatched_fiducial_indices),
            "sigma_px": f(self.sigma_px), "used_prior": self.used_prior,
            "timing": {k: float(v) for k, v in self.timing.items()},
        }

    def __repr__(self) -> str:  # short, for logs
        if not self.ok:
            return f"Registration(ok=False, method={self.method!r}, reason={self.reason!r})"
        return (f"Registration(ok=True, method={self.method!r}, pairs={len(self.pairs)}, "
                f"rms={self.reprojection_rms_px:.2f}px, fre={self.fre_mm:.2f}mm, "
                f"t={1000 * self.timing.get('total_s', float('nan')):.1f}ms)")
