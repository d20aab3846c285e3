"""Deciding whether a pose estimate may drive the arm: the session's one trust verdict.

Built once from ``SessionConfig`` (:meth:`PoseGate.from_config`), in two stages that share its
limits: ``SessionConfig.frame_rules()`` are the per-frame rules vision's ``PoseTracker`` applies to every
estimate of every camera rig (the rig factory hands them to each rig: ``min_fiducials``, the
residual gates, physical plausibility, weak geometry, the predicted-TRE bound with its noise
upper bound and tail probability), and :meth:`PoseGate.check` judges each estimate the rig
delivers, over time. A pose is *trusted* when all hold:

1. the estimator says ``ok``;
2. at least ``min_fiducials`` fiducials were matched (the paper needs >= 4 for < 1 mm);
3. its FRE is at most ``max_fre_mm``, and its predicted error at the planned target at most
   ``max_predicted_tre_mm`` (1 mm; FRE does not predict TRE, the propagated covariance does);
4. it is consistent with the recent past: within ``max_jump_mm`` (at the planned entry) and
   ``max_jump_deg`` of the last trusted pose, if that is younger than ``reference_max_age_s``.
   Otherwise (a jump, or no recent reference: first lock, or after an occlusion) the pose is only
   trusted once ``confirm_frames`` consecutive estimates agree with each other within the same
   bounds. A single wrong estimate (a mismatched fiducial, a reflection) therefore never moves
   the arm, while a real head movement is followed after ``confirm_frames`` frames.

An invalid estimate keeps the alert code its estimator gave (``code``: ``camera_ended``,
``frame_size``, ``frame_unreadable``, ``tre_limit``, ...), so the operator reads what happened;
without one, fewer than ``min_fiducials`` matched is ``occlusion`` and anything else
``estimator``.

Rules 2 and 3 repeat what the frame rules already refused for a rig that runs them, with the same
limits; they stand for a rig that does not (a test double delivering samples of its own).

The gate is pure bookkeeping (no threads, no clock of its own): the loop feeds it each estimate
with its capture time and reads a :class:`GateVerdict`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monotracker.geometry import pose_jump


@dataclass(frozen=True)
class GateVerdict:
    trusted: bool
    code: str  # "ok" | "estimator" | "occlusion" | "fre" | "tre_limit" | "jump" | "acquiring" | an estimator's code
    reason: str


class PoseGate:
    """The trust verdict of each estimate (see the module docstring); :meth:`from_config` builds
    the session's one gate from its configuration."""

    @classmethod
    def from_config(cls, cfg) -> "PoseGate":
        """The gate of a session: every limit from its ``SessionConfig`` (mm, deg, frames);
        ``frame_rules`` are the per-frame rules its camera rigs apply (``SessionConfig.frame_rules``)."""
        gate = cls(cfg.min_fiducials, cfg.max_fre_mm, cfg.max_jump_mm, cfg.max_jump_deg, cfg.confirm_frames,
                   max_predicted_tre_mm=cfg.max_predicted_tre_mm)
        gate.frame_rules = cfg.frame_rules()
        return gate

    def __init__(self, min_fiducials: int = 4, max_fre_mm: float = 1.5, max_jump_mm: float = 5.0,
                 max_jump_deg: float = 3.0, confirm_frames: int = 3, reference_max_age_s: float = 0.5,
                 max_predicted_tre_mm: float = 1.0):
        self.min_fiducials = int(min_fiducials)
        self.max_predicted_tre_mm = float(max_predicted_tre_mm)
        self.max_fre_mm = float(max_fre_mm)
        self.max_jump_mm = float(max_jump_mm)
        self.max_jump_deg = float(max_jump_deg)
        self.confirm_frames = max(1, int(confirm_frames))
        self.reference_max_age_s = float(reference_max_age_s)
        self.about_ct = np.zeros(3)
        self._ref_T: np.ndarray | None = None
        self._ref_t = -np.inf
        self._candidates: list[np.ndarray] = []

    def set_anchor(self, about_ct: np.ndarray) -> None:
        """CT point (mm) where jumps are measured: the planned entry (or the fiducial centroid)."""
        self.about_ct = np.asarray(about_ct, float).copy()

    def reset(self) -> None:
        self._ref_T, self._ref_t, self._candidates = None, -np.inf, []

    def _close(self, A: np.ndarray, B: np.ndarray) -> tuple[bool, float, float]:
        d_mm, d_deg = pose_jump(A, B, self.about_ct)
        return (d_mm <= self.max_jump_mm and d_deg <= self.max_jump_deg), d_mm, d_deg

    def check(self, ok: bool, reason: str, T_cam_ct, n_matched: int, fre_mm, t_capture: float,
              code: str = "", predicted_tre_mm=None) -> GateVerdict:
        """``code``: the estimator's alert code for an invalid estimate ('' if none);
        ``predicted_tre_mm``: predicted error at the planned target (None = not available)."""
        if not ok or T_cam_ct is None:
            self._candidates = []
            if not code:
                code = "occlusion" if n_matched < self.min_fiducials else "estimator"
            return GateVerdict(False, code, reason or "no pose")
        if n_matched < self.min_fiducials:
            self._candidates = []
            return GateVerdict(False, "occlusion", f"only {n_matched} fiducials matched (need {self.min_fiducials})")
        if fre_mm is not None and np.isfinite(fre_mm) and fre_mm > self.max_fre_mm:
            self._candidates = []
            return GateVerdict(False, "fre", f"FRE {fre_mm:.2f} mm exceeds {self.max_fre_mm:.2f} mm")
        if predicted_tre_mm is not None and not (predicted_tre_mm <= self.max_predicted_tre_mm):
            self._candidates = []
            return GateVerdict(False, "tre_limit", f"predicted error at the target {predicted_tre_mm:.2f} mm "
                                                   f"exceeds {self.max_predicted_tre_mm:.2f} mm")
        T = np.asarray(T_cam_ct, float)
        if self._ref_T is not None and t_capture - self._ref_t <= self.reference_max_age_s:
            close, d_mm, d_deg = self._close(self._ref_T, T)
            if close:
                self._accept(T, t_capture)
                return GateVerdict(True, "ok", "pose trusted")
            why = f"pose jumped {d_mm:.1f} mm / {d_deg:.1f} deg since the last trusted pose"
            code = "jump"
        else:
            why = "acquiring: waiting for consistent poses"
            code = "acquiring"
        # Need confirm_frames consecutive, mutually consistent estimates.
        if self._candidates and not self._close(self._candidates[-1], T)[0]:
            self._candidates = []
        self._candidates.append(T)
        if len(self._candidates) >= self.confirm_frames:
            self._accept(T, t_capture)
            return GateVerdict(True, "ok", f"pose confirmed by {self.confirm_frames} consistent frames")
        return GateVerdict(False, code, f"{why}; confirming ({len(self._candidates)} of {self.confirm_frames} "
                                        "consistent frames)")

    def check_sample(self, sample) -> GateVerdict:
        """:meth:`check` of a rig's :class:`~monotracker.engine.rigs.base.PoseSample` (a vision
        estimate becomes one through ``rigs.base.estimate_to_sample``): how the tracking loop
        feeds every estimate, and how a benchmark or test replays what may move the arm."""
        return self.check(sample.ok, sample.reason, sample.T_cam_ct, sample.n_matched, sample.fre_mm,
                          sample.t_capture, code=getattr(sample, "code", ""), predicted_tre_mm=sample.predicted_tre_mm)

    def _accept(self, T: np.ndarray, t: float) -> None:
        self._ref_T, self._ref_t, self._candidates = T, t, []
