"""The error at the target a layout and a camera pose will give, before the patient is there.

The model is the registration's own (:mod:`monotracker.registration.report`): the pose
covariance ``sigma^2 (J^T J)^-1`` with the refinement's Jacobian at the planned pose (each
seen ball's share from :func:`~monotracker.registration.report.fiducial_information`), pushed to
the target (:func:`~monotracker.registration.report.target_covariance`); the pose stream's
predicted TRE is this number once frames come. Here ``sigma`` is the planned image noise (px),
and only the balls the camera sees count (:mod:`.visibility`). As the pose tracker does with the
default edge-fitted detector, each ball's error is at least its edge spread and a shift common to
all balls is added (:func:`.trust.shading_cover`; the problem's ``edge_rms_px``, by default the
planned noise): the covariance is ``max(sigma, floor)^2 C1 + C0``.

Each error is reported as the RMS 3D error (what the tracker gates on), and the mean and the
95th percentile of its length (the Gaussian's, :func:`~monotracker.registration.report.error_norm_stats`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from monotracker.geometry import invert_transform
from monotracker.registration.report import (common_shift_covariance, error_norm_stats, fiducial_jacobian,
                                             pose_covariance, target_covariance)
from monotracker.vision.pose_checks import weak_geometry
from monotracker.vision.tracker_config import TrackerConfig

from .ball_losses import LossOutlook, loss_outlook
from .detector_defaults import SHORT_OF_SKIN_FOUND_RATIO
from .trust import gate_noise_px, shading_cover, trusted_fraction
from .visibility import Visibility, visibility


@dataclass(frozen=True)
class TargetError:
    """Predicted error at the target with ``n_balls`` seen balls: ``rms_mm`` (sqrt of the
    covariance's trace), ``mean_mm`` and ``p95_mm`` of its length, ``cov_mm2`` (3, 3) in the
    camera frame; ``trusted`` the predicted share of frames the pose stream trusts;
    ``gate_noise_px`` the largest image noise its gates let through; ``floor_px`` and
    ``common_px`` the shading cover modelled (:func:`.trust.shading_cover`; 0 without);
    ``common_mm2`` the common shift's share of the covariance's trace (mm^2)."""

    n_balls: int
    rms_mm: float
    mean_mm: float
    p95_mm: float
    cov_mm2: np.ndarray
    trusted: float
    gate_noise_px: float
    floor_px: float = 0.0
    common_px: float = 0.0
    common_mm2: float = 0.0

    def to_dict(self) -> dict:
        return {"balls_seen": self.n_balls, "rms_mm": round(self.rms_mm, 4), "mean_mm": round(self.mean_mm, 4),
                "p95_mm": round(self.p95_mm, 4), "trusted_fraction": round(self.trusted, 4),
                "gate_noise_px": round(self.gate_noise_px, 4), "shading_floor_px": round(self.floor_px, 4),
                "common_shift_px": round(self.common_px, 4)}


def pose_problem(fiducials_ct: np.ndarray, seen: np.ndarray, config: TrackerConfig | None = None) -> str:
    """'' when the seen balls can give a trusted pose (enough of them, not collinear or
    coplanar: the tracker's :func:`~monotracker.vision.pose_checks.weak_geometry`), else why not."""
    cfg = config or TrackerConfig()
    return weak_geometry(fiducials_ct, list(np.flatnonzero(seen)), cfg.min_fiducials)


def predict_error(problem, T_ct_cam: np.ndarray, centres: np.ndarray, seen: np.ndarray,
                  noise_px: float | None = None, config: TrackerConfig | None = None,
                  frames: int = 300, full: bool = True) -> TargetError | None:
    """:class:`TargetError` of the balls ``centres[seen]`` (LPS mm) from ``T_ct_cam`` at image
    noise ``noise_px`` (None: the problem's); None when they cannot give a trusted pose
    (:func:`pose_problem`). ``full`` False: the RMS only (mean, p95, trusted share and gate
    noise NaN), for live use (a fraction of a millisecond)."""
    C = np.asarray(centres, float).reshape(-1, 3)
    seen = np.asarray(seen, bool)
    if pose_problem(C, seen, config):
        return None
    sigma = problem.noise_px if noise_px is None else float(noise_px)
    floor, common = shading_cover(sigma, problem.edge_rms_px, config, int(seen.sum()))
    T_cam_ct = invert_transform(np.asarray(T_ct_cam, float))
    fxy = np.array([problem.camera.K[0, 0], problem.camera.K[1, 1]])
    J = fiducial_jacobian(T_cam_ct, C[seen], fxy, problem.radius_mm)           # (k, 2, 6)
    info = np.einsum("kai,kaj->ij", J, J)
    cov1 = target_covariance(T_cam_ct, pose_covariance(info, 1.0), problem.target)
    fixed = np.zeros((3, 3))
    if common > 0:
        fixed = target_covariance(T_cam_ct, common_shift_covariance(J.reshape(-1, 6), common), problem.target)
    cov = cov1 * max(sigma, floor) ** 2 + fixed
    rms = float(np.sqrt(max(np.trace(cov), 0.0)))
    k = int(seen.sum())
    c0 = float(np.trace(fixed))
    if not full:
        nan = float("nan")
        return TargetError(k, rms, nan, nan, cov, nan, nan, floor, common, c0)
    mean, p95 = error_norm_stats(cov, 0.95)
    return TargetError(k, rms, mean, p95, cov,
                       trusted_fraction(cov1, k, sigma, frames, config, floor_px=floor, fixed_cov3=fixed),
                       gate_noise_px(cov1, config, floor, fixed), floor, common, c0)


def outlook_with_losses(problem, T_ct_cam: np.ndarray, centres: np.ndarray, seen: np.ndarray,
                        found_probability: float | None = None, noise_px: float | None = None,
                        config: TrackerConfig | None = None, short_of_skin: np.ndarray | None = None,
                        short_ratio: float = SHORT_OF_SKIN_FOUND_RATIO, **kw) -> LossOutlook:
    """:func:`~.ball_losses.loss_outlook` of the balls ``centres[seen]`` (LPS mm) from
    ``T_ct_cam``, each pattern of found balls predicted by :func:`predict_error`;
    ``found_probability`` None: the problem's, the chance of a ball with skin all round it;
    ``short_of_skin`` (n,) bool: balls with too little skin around them in the camera's view
    (``Visibility.short_of_skin``), found with ``short_ratio`` times that chance (None: every
    ball alike). ``kw``: ``per_count``, ``min_weight``, ``seed``."""
    C = np.asarray(centres, float).reshape(-1, 3)
    q = problem.found_probability if found_probability is None else float(found_probability)
    seen = np.asarray(seen, bool)
    short = np.zeros(len(C), bool) if short_of_skin is None else np.asarray(short_of_skin, bool) & seen
    q_each = np.where(short, q * float(short_ratio), q)
    out = loss_outlook(lambda keep: predict_error(problem, T_ct_cam, C, keep, noise_px, config), seen, q_each, **kw)
    return replace(out, found_probability=q, found_short=None if short_of_skin is None else q * float(short_ratio),
                   short_of_skin=int(short.sum()))


@dataclass(frozen=True)
class Prediction:
    """What to expect from balls ``centres`` (n, 3) LPS mm seen from ``T_ct_cam`` (4x4).

    ``visibility``: which balls the camera sees and why not the others; ``all_seen``: the error at
    the target with every seeable ball (None: they cannot give a pose; ``reason`` says why);
    ``worst_hidden``: the error when the one ball whose loss hurts most is hidden too
    (``worst_ball`` its index; None when losing any one ball loses the pose: ``margin_reason``);
    ``with_losses`` the outlook when the detector finds each seen ball with the problem's
    ``found_probability`` (:mod:`.ball_losses`; None unless asked for);
    ``noise_px`` the image noise assumed; ``distance_mm`` camera to the seen balls' centroid."""

    T_ct_cam: np.ndarray
    centres: np.ndarray
    visibility: Visibility
    all_seen: TargetError | None
    worst_hidden: TargetError | None
    worst_ball: int | None
    noise_px: float
    distance_mm: float
    reason: str = ""
    margin_reason: str = ""
    with_losses: LossOutlook | None = None

    def to_dict(self) -> dict:
        return {
            "T_ct_cam": np.round(self.T_ct_cam, 6).tolist(),
            "camera_distance_mm": round(self.distance_mm, 1),
            "noise_px": self.noise_px,
            "balls_seen": self.visibility.count,
            "hidden": {str(i): w for i, w in enumerate(self.visibility.why) if w},
            # per seen ball, the share of its surroundings in the image that is exposed skin
            "skin_around": {str(i): round(float(a), 3) for i, a in enumerate(self.visibility.skin_around)
                            if self.visibility.seen[i]} if self.visibility.skin_around is not None else None,
            "all_seen": None if self.all_seen is None else self.all_seen.to_dict(),
            "worst_hidden_ball": self.worst_ball,
            "worst_hidden": None if self.worst_hidden is None else self.worst_hidden.to_dict(),
            "with_detector_losses": None if self.with_losses is None else self.with_losses.to_dict(),
            "reason": self.reason, "margin_reason": self.margin_reason,
        }


def predict(problem, T_ct_cam: np.ndarray, centres: np.ndarray, normals: np.ndarray | None = None,
            noise_px: float | None = None, config: TrackerConfig | None = None, full: bool = True,
            losses: bool = False) -> Prediction:
    """The :class:`Prediction` for balls ``centres`` (n, 3) LPS mm with skin normals ``normals``
    (None: estimated from the head surface around each ball) and a camera at ``T_ct_cam``.
    ``full`` False: RMS errors only (see :func:`predict_error`), cheap enough to run live;
    ``losses``: also the outlook with the detector's losses (``with_losses``; ~0.5 s)."""
    from .candidates import skin_normals_under

    C = np.asarray(centres, float).reshape(-1, 3)
    N = skin_normals_under(problem.head, C, problem.radius_mm) if normals is None else np.asarray(normals, float)
    vis = visibility(problem, T_ct_cam, C, N)
    sigma = problem.noise_px if noise_px is None else float(noise_px)
    eye = np.asarray(T_ct_cam, float)[:3, 3]
    dist = float(np.linalg.norm(C[vis.seen].mean(axis=0) - eye)) if vis.count else float("nan")
    allp = predict_error(problem, T_ct_cam, C, vis.seen, sigma, config, full=full)
    outlook = (outlook_with_losses(problem, T_ct_cam, C, vis.seen, noise_px=sigma, config=config,
                                   short_of_skin=vis.short_of_skin) if losses else None)
    if allp is None:
        why = pose_problem(C, vis.seen, config)
        return Prediction(np.asarray(T_ct_cam, float), C, vis, None, None, None, sigma, dist,
                          reason=f"{vis.count} of {len(C)} balls seen: {why}", with_losses=outlook)
    worst, worst_i, margin = None, None, ""
    for i in np.flatnonzero(vis.seen):
        s = vis.seen.copy()
        s[i] = False
        e = predict_error(problem, T_ct_cam, C, s, sigma, config, full=full)
        if e is None:
            worst, worst_i = None, int(i)
            margin = f"hiding ball {i} leaves {int(s.sum())} seen: {pose_problem(C, s, config)}"
            break
        if worst is None or e.rms_mm > worst.rms_mm:
            worst, worst_i = e, int(i)
    return Prediction(np.asarray(T_ct_cam, float), C, vis, allp, worst, worst_i, sigma, dist, margin_reason=margin,
                      with_losses=outlook)
