"""Pose refinement: Levenberg-Marquardt on reprojection error over all matched points.

Parametrisation: a left perturbation of ``T_cam_ct``: ``R <- exp([w]x) R``, ``t <- t + dt``
(w in rad, dt in mm, both in the camera frame). Residuals are normalised-plane residuals
times (fx, fy), i.e. equivalent pinhole pixels. The Jacobian is
analytic, including the exact sphere-bias model (``radius_mm``): for a centre (a, b, c)
the prediction is (a, b) s(c) with s = c / (c^2 - R^2), ds/dc = -(c^2 + R^2) / (c^2 - R^2)^2. Our own LM rather than ``cv2.solvePnPRefineLM`` because
the latter knows nothing of the ellipse-centre model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .projection import project_normalised


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) for rotation vectors w (..., 3) (Rodrigues)."""
    w = np.asarray(w, dtype=float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -w[..., 2], w[..., 1]
    K[..., 1, 0], K[..., 1, 2] = w[..., 2], -w[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -w[..., 1], w[..., 0]
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    A = np.where(small, 1.0, np.sin(ths) / ths)
    B = np.where(small, 0.5, (1 - np.cos(ths)) / ths**2)
    return np.eye(3) + A * K + B * (K @ K)


@dataclass
class Refinement:
    T: np.ndarray            # 4x4 T_cam_ct
    residuals: np.ndarray    # (k, 2) equivalent px (unweighted)
    JtJ: np.ndarray          # (6, 6) Gauss-Newton normal matrix at the optimum (px^2 units; J^T W J when weighted)
    iterations: int
    converged: bool
    #: (2k, 6) Jacobian of the (unweighted) residuals at the optimum, px per (rad, mm)
    J: np.ndarray | None = None


def _residuals(R, t, X, obs, fxy, radius_mm):
    Xc = np.einsum("...ij,kj->...ki", R, X) + t[..., None, :]
    return (project_normalised(Xc, radius_mm) - obs) * fxy


def _residuals_and_jacobian(R, t, X, obs, fxy, radius_mm):
    """Residuals r (2k,) px and analytic Jacobian (2k, 6) px per (rad, mm) w.r.t. the left
    perturbation (w, dt): compiled (:mod:`.pnp_kernels`), same as
    :func:`residuals_and_jacobian_reference`."""
    from . import pnp_kernels

    X = np.ascontiguousarray(X, dtype=float).reshape(-1, 3)
    k = len(X)
    r, J = np.empty(2 * k), np.empty((2 * k, 6))
    pnp_kernels.residuals_and_jacobian(np.ascontiguousarray(R, dtype=float), np.ascontiguousarray(t, dtype=float),
                                       X, np.ascontiguousarray(obs, dtype=float).reshape(-1, 2),
                                       float(fxy[0]), float(fxy[1]), float(radius_mm or 0.0), _NO_WEIGHTS, r, J)
    return r, J


_NO_WEIGHTS = np.empty(0)


def residuals_and_jacobian_reference(R, t, X, obs, fxy, radius_mm):
    """The NumPy form of :func:`_residuals_and_jacobian` (the compiled kernel's reference)."""
    q = X @ R.T                      # R X (k, 3)
    Xc = q + t
    a, b, c = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    if radius_mm:
        den = c * c - radius_mm * radius_mm
        s = c / den
        ds = -(c * c + radius_mm * radius_mm) / (den * den)   # d s / d c
    else:
        s = 1.0 / c
        ds = -1.0 / (c * c)
    r = (np.stack([a * s, b * s], axis=1) - obs) * fxy
    k = len(X)
    # d proj / d Xc  (k, 2, 3)
    Dp = np.zeros((k, 2, 3))
    Dp[:, 0, 0] = s
    Dp[:, 1, 1] = s
    Dp[:, 0, 2] = a * ds
    Dp[:, 1, 2] = b * ds
    Dp *= fxy[None, :, None]
    # d Xc / d w = -[q]x ; d Xc / d dt = I
    Qx = np.zeros((k, 3, 3))
    Qx[:, 0, 1], Qx[:, 0, 2] = q[:, 2], -q[:, 1]
    Qx[:, 1, 0], Qx[:, 1, 2] = -q[:, 2], q[:, 0]
    Qx[:, 2, 0], Qx[:, 2, 1] = q[:, 1], -q[:, 0]
    J = np.concatenate([Dp @ Qx, Dp], axis=2).reshape(2 * k, 6)
    return r.ravel(), J


def refine_pose(T0: np.ndarray, X: np.ndarray, obs: np.ndarray, fxy: np.ndarray,
                radius_mm: float | None = None, max_iter: int = 20, tol: float = 1e-9,
                weights: np.ndarray | None = None) -> Refinement:
    """LM refinement of ``T0`` (4x4 T_cam_ct, mm) for model points X (k, 3) CT mm and normalised
    observations obs (k, 2); ``fxy`` = (fx, fy) converts residuals to pixels. ``weights`` (k,):
    each point's weight in the least squares (e.g. the number of frames averaged into it); None =
    equal. Compiled (:mod:`.pnp_kernels`); :func:`refine_pose_reference` is the same in NumPy."""
    from . import pnp_kernels

    X = np.ascontiguousarray(X, dtype=float).reshape(-1, 3)
    obs = np.ascontiguousarray(obs, dtype=float).reshape(-1, 2)
    T0 = np.asarray(T0, float)
    fx, fy, radius = float(fxy[0]), float(fxy[1]), float(radius_mm or 0.0)
    sw = _NO_WEIGHTS if weights is None else np.repeat(np.sqrt(np.asarray(weights, float).reshape(-1)), 2)
    R, t, it, converged, JtJ = pnp_kernels.refine(np.ascontiguousarray(T0[:3, :3]), np.ascontiguousarray(T0[:3, 3]),
                                                  X, obs, fx, fy, radius, sw, int(max_iter), float(tol))
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    k = len(X)
    r0, J0 = np.empty(2 * k), np.empty((2 * k, 6))
    pnp_kernels.residuals_and_jacobian(R, t, X, obs, fx, fy, radius, _NO_WEIGHTS, r0, J0)
    return Refinement(T=T, residuals=r0.reshape(-1, 2), JtJ=JtJ, iterations=int(it), converged=bool(converged), J=J0)


def refine_pose_reference(T0: np.ndarray, X: np.ndarray, obs: np.ndarray, fxy: np.ndarray,
                          radius_mm: float | None = None, max_iter: int = 20, tol: float = 1e-9,
                          weights: np.ndarray | None = None) -> Refinement:
    """The NumPy form of :func:`refine_pose` (the compiled kernel's reference)."""
    R = T0[:3, :3].copy()
    t = T0[:3, 3].copy()
    lam = 1e-3
    sw = None if weights is None else np.repeat(np.sqrt(np.asarray(weights, float).reshape(-1)), 2)

    def _rj(R_, t_):
        r_, J_ = residuals_and_jacobian_reference(R_, t_, X, obs, fxy, radius_mm)
        return (r_, J_) if sw is None else (r_ * sw, J_ * sw[:, None])

    r, J = _rj(R, t)
    cost = r @ r
    converged = False
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - the count is reported after the loop
        JtJ = J.T @ J
        g = J.T @ r
        improved = False
        rel = 0.0
        dx = np.zeros(6)
        for _ in range(8):
            A = JtJ + lam * np.diag(np.diag(JtJ) + 1e-12)
            try:
                dx = -np.linalg.solve(A, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            Rn = so3_exp(dx[:3]) @ R
            tn = t + dx[3:]
            rn, Jn = _rj(Rn, tn)
            cn = rn @ rn
            if np.isfinite(cn) and cn <= cost:
                rel = (cost - cn) / max(cost, 1e-30)
                R, t, r, J, cost = Rn, tn, rn, Jn, cn
                lam = max(lam * 0.3, 1e-9)
                improved = True
                break
            lam *= 10
        if not improved or rel < tol or np.linalg.norm(dx) < 1e-12:
            converged = True
            break
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    r0, J0 = residuals_and_jacobian_reference(R, t, X, obs, fxy, radius_mm)
    return Refinement(T=T, residuals=r0.reshape(-1, 2), JtJ=J.T @ J, iterations=it, converged=converged, J=J0)
