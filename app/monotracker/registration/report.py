"""Accuracy report of a monocular registration.

Definitions (the paper's FRE/TRE are 3D distances; a single camera measures rays, so we
choose, and document, the monocular equivalents):

* **FRE** (mm): RMS over matched fiducials of the 3D distance between the fiducial mapped by
  ``T_cam_ct`` into the camera frame and the viewing ray of its image point. With the sphere
  model the ray is the one through the *sphere centre* implied by the observed ellipse centre
  (ellipse centre e, depth c: centre direction = e (1 - R^2 / c^2)).
* **Reprojection residuals** (px): per pair, observed minus predicted image position, in
  equivalent pinhole pixels (normalised residual times fx, fy).
* **TRE** (mm) against a reference pose: ``||T_est p - T_ref p||`` for target points p (CT mm),
  i.e. the error in the camera frame where the robot uses the pose.
* **Predicted TRE** (mm) at a target: first-order propagation of the pose covariance
  ``sigma^2 (J^T J)^-1`` (J the reprojection Jacobian at the optimum) to the target position;
  sigma (px) is estimated from the residuals with 2k - 6 degrees of freedom (k pairs, 6 pose
  parameters): ``sigma^2 = RSS / (2k - 6)`` is unbiased for Gaussian noise, so the prediction is
  calibrated (within +-20 % of Monte-Carlo truth from 0.1 to 0.5 px,
  ``tests/registration/test_noise_calibration.py``). There is no floor: the former 0.3 px floor
  made the prediction 3x too high at 0.1 px noise. With few dof the single-frame estimate is
  itself noisy; the pose stream pools it over frames (:mod:`.noise`). The value is the RMS 3D
  error sqrt(trace(Cov_p)).
"""

from __future__ import annotations

import numpy as np

#: Numerical lower bound on the image noise (px): only keeps the covariance non-zero for an
#: exact fit; far below any real detector, so it hides nothing.
SIGMA_FLOOR_PX = 1e-3
#: The floor used before (kept for the benchmark's baseline): it hid low noise.
LEGACY_SIGMA_FLOOR_PX = 0.3


def residual_dof(n_pairs: int) -> int:
    """Residual degrees of freedom of a 6-dof pose fit to ``n_pairs`` 2D points."""
    return max(2 * int(n_pairs) - 6, 0)


def sigma_from_residuals(residuals_px: np.ndarray, floor_px: float = SIGMA_FLOOR_PX) -> float:
    """Per-coordinate image noise (px) estimated from (k, 2) residuals of a 6-dof fit:
    ``sqrt(RSS / (2k - 6))`` (unbiased variance), never below ``floor_px``."""
    r = np.asarray(residuals_px, dtype=float).reshape(-1)
    dof = r.size - 6
    est = float(np.sqrt(r @ r / dof)) if dof > 0 else 0.0
    return max(est, floor_px)


def pose_covariance(JtJ: np.ndarray, sigma_px: float) -> np.ndarray:
    """(6, 6) covariance of the left-perturbation pose parameters (rad, mm); a stack
    (..., 6, 6) of normal matrices gives a stack of covariances."""
    return sigma_px**2 * np.linalg.pinv(JtJ)


def fiducial_jacobian(T_cam_ct: np.ndarray, fiducials_ct: np.ndarray, fxy: np.ndarray,
                      radius_mm: float | None = None) -> np.ndarray:
    """(k, 2, 6) each fiducial's rows of the refinement's own Jacobian (px per rad / mm;
    equivalent pinhole px, sphere-centre model when ``radius_mm``; :mod:`.pnp`) of a pose fit at
    ``T_cam_ct``: what a frame's fit would have, before the frame exists (layout planning)."""
    from .pnp import _residuals_and_jacobian

    T = np.asarray(T_cam_ct, float)
    X = np.asarray(fiducials_ct, float).reshape(-1, 3)
    _, J = _residuals_and_jacobian(T[:3, :3], T[:3, 3], X, np.zeros((len(X), 2)),
                                   np.asarray(fxy, float).reshape(2), radius_mm)
    return J.reshape(len(X), 2, 6)


def fiducial_information(T_cam_ct: np.ndarray, fiducials_ct: np.ndarray, fxy: np.ndarray,
                         radius_mm: float | None = None) -> np.ndarray:
    """(k, 6, 6) each fiducial's share ``J_i^T J_i`` (px^2 per rad^2 / mm^2) of the normal
    matrix of a pose fit at ``T_cam_ct`` (:func:`fiducial_jacobian`). Summed over the fiducials
    a frame matches it is the ``JtJ`` :func:`pose_covariance` takes: the registration's
    covariance before the frame exists (layout planning), from the same code."""
    J = fiducial_jacobian(T_cam_ct, fiducials_ct, fxy, radius_mm)
    return np.einsum("kai,kaj->kij", J, J)


def target_covariance(T_cam_ct: np.ndarray, cov6: np.ndarray, target_ct: np.ndarray) -> np.ndarray:
    """(3, 3) covariance (mm^2, camera frame) of one target point (3,) CT mm under the pose
    covariance ``cov6`` (rotation vector rad, translation mm; left perturbation); a stack
    ``cov6`` (..., 6, 6) gives a stack (..., 3, 3)."""
    q = T_cam_ct[:3, :3] @ np.asarray(target_ct, float).reshape(3)
    J = np.zeros((3, 6))
    J[:, :3] = -np.array([[0, -q[2], q[1]], [q[2], 0, -q[0]], [-q[1], q[0], 0]])
    J[:, 3:] = np.eye(3)
    return J @ cov6 @ J.T


def predicted_tre(T_cam_ct: np.ndarray, cov6: np.ndarray, target_ct: np.ndarray) -> np.ndarray:
    """Predicted RMS 3D error (mm) at target(s) (3,) or (k, 3) in CT mm."""
    P = np.atleast_2d(np.asarray(target_ct, dtype=float))
    out = np.array([np.sqrt(max(np.trace(target_covariance(T_cam_ct, cov6, p)), 0.0)) for p in P])
    return out if np.ndim(target_ct) > 1 else out[0]


_STD_NORMAL_3D = np.random.default_rng(20240613).standard_normal((40000, 3))
#: the same draws ordered by their squared norm (ascending), and those norms: only the draws with
#: sd_max^2 |z|^2 > r^2 can exceed r, so the estimate needs only the tail (the same count)
_ORDER = np.argsort((_STD_NORMAL_3D**2).sum(axis=1), kind="stable")
_BY_NORM = _STD_NORMAL_3D[_ORDER]
_NORM2 = (_BY_NORM**2).sum(axis=1)


def exceed_probability(cov3: np.ndarray, r_mm: float) -> float:
    """P(|e| > r_mm) for a zero-mean Gaussian 3D error with covariance ``cov3`` (mm^2):
    a deterministic Monte-Carlo estimate over 40 000 fixed standard-normal draws (resolution
    2.5e-5; the norm of a correlated Gaussian has no closed form)."""
    w, V = np.linalg.eigh(np.asarray(cov3, float))
    sd = np.sqrt(np.clip(w, 0.0, None))
    sd_max = float(sd.max())
    if sd_max <= 0.0:
        return 0.0
    # (z sd)^2 summed <= sd_max^2 |z|^2: the draws below that bound cannot count (margin for rounding)
    first = int(np.searchsorted(_NORM2, (1.0 - 1e-9) * r_mm**2 / sd_max**2, side="left"))
    d2 = (_BY_NORM[first:] * sd) ** 2
    return float(np.count_nonzero(d2.sum(axis=1) > r_mm**2) / len(_STD_NORMAL_3D))


def error_norm_stats(cov3: np.ndarray, quantile: float = 0.95) -> tuple[float, float]:
    """(mean, ``quantile``) of the length |e| (mm) of a zero-mean Gaussian 3D error with
    covariance ``cov3`` (mm^2), over the same 40 000 fixed draws as :func:`exceed_probability`."""
    w, _ = np.linalg.eigh(np.asarray(cov3, float))
    norms = np.sqrt(((_STD_NORMAL_3D * np.sqrt(np.clip(w, 0.0, None))) ** 2).sum(axis=1))
    return float(norms.mean()), float(np.quantile(norms, quantile))


def tre_mm(T_est: np.ndarray, T_ref: np.ndarray, targets_ct: np.ndarray) -> np.ndarray:
    """(k,) distances (mm) between targets mapped by the estimated and the reference pose."""
    P = np.atleast_2d(np.asarray(targets_ct, dtype=float))
    a = P @ T_est[:3, :3].T + T_est[:3, 3]
    b = P @ T_ref[:3, :3].T + T_ref[:3, 3]
    return np.linalg.norm(a - b, axis=1)


def fre_mm(T_cam_ct: np.ndarray, X_ct: np.ndarray, xn: np.ndarray, radius_mm: float | None) -> float:
    """Monocular FRE (mm): RMS point-to-ray distance, see the module docstring."""
    if len(X_ct) == 0:
        return float("nan")
    Xc = X_ct @ T_cam_ct[:3, :3].T + T_cam_ct[:3, 3]
    xy = np.asarray(xn, dtype=float)
    if radius_mm:
        xy = xy * (1.0 - radius_mm**2 / Xc[:, 2:3] ** 2)
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    along = np.sum(Xc * d, axis=1, keepdims=True)
    perp = Xc - along * d
    return float(np.sqrt(np.mean(np.sum(perp**2, axis=1))))


def common_shift_covariance(J: np.ndarray, sigma_px: float, A: np.ndarray | None = None) -> np.ndarray:
    """(6, 6) pose covariance (rotation vector rad, translation mm) that a shift shared by all
    image points leaves in a least-squares fit with Jacobian ``J`` ((2k, 6), px per parameter,
    rows x0, y0, x1, y1, ...): the shift is ``N(0, sigma_px^2 I2)``, the same vector for every
    point, so its image covariance is ``sigma^2 (1 1^T kron I2)`` and the fit passes it on as
    ``A C A^T`` with ``A = (J^T J)^-1 J^T`` (pass ``A`` (6, 2k) when the caller has it: one
    pseudo-inverse a frame less). The residuals cannot show such a shift."""
    J = np.asarray(J, float)
    k = J.shape[0] // 2
    if A is None:
        A = np.linalg.pinv(J.T @ J) @ J.T
    S = np.tile(np.eye(2), (k, 1))                  # (2k, 2): each point moves by the same 2-vector
    B = A @ S
    return float(sigma_px) ** 2 * (B @ B.T)


def layout_units(points_px: np.ndarray) -> np.ndarray:
    """(k, 2) the points about their centroid over their RMS distance from it (unit-free; RMS
    norm 1): the coordinates a bias that changes linearly across the layout is written in."""
    P = np.asarray(points_px, float).reshape(-1, 2)
    u = P - P.mean(axis=0)
    L = float(np.sqrt(np.mean(np.sum(u**2, axis=1))))
    return u / L if L > 0 else np.zeros_like(u)


def layout_gradient_covariance(J: np.ndarray, points_px: np.ndarray, sigma_px: float,
                               A: np.ndarray | None = None) -> np.ndarray:
    """(6, 6) pose covariance that an image error changing linearly across the points leaves in
    a least-squares fit with Jacobian ``J`` ((2k, 6), rows x0, y0, x1, y1, ...): point i moves by
    ``G u_i`` (``u_i``: :func:`layout_units` of ``points_px`` (k, 2)), G a 2x2 matrix of
    independent ``N(0, sigma_px^2)`` entries, so the image covariance is ``sigma^2 (U U^T kron
    I2)``; the fit passes it on as ``A C A^T`` with ``A = (J^T J)^-1 J^T``. A pose absorbs most
    of such a field (a tilt or a change of depth moves the image so), so the residuals show
    little of it."""
    J = np.asarray(J, float)
    k = J.shape[0] // 2
    if A is None:
        A = np.linalg.pinv(J.T @ J) @ J.T
    u = layout_units(points_px)
    if u.shape[0] != k:
        raise ValueError(f"{u.shape[0]} points for a Jacobian of {k}")
    S = np.zeros((2 * k, 4))                        # columns: G_xx, G_xy, G_yx, G_yy
    S[0::2, 0:2] = u
    S[1::2, 2:4] = u
    B = A @ S
    return float(sigma_px) ** 2 * (B @ B.T)
