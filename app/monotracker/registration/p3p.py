"""Vectorised perspective-three-point solver (Grunert's quartic, as reviewed by Haralick et al.
1994), batched over many (bearing triplet, model triplet) hypotheses at once.

Why our own: the robust search tests hundreds of triplet pairs per image; a Python loop over
``cv2.solveP3P`` costs ~20 us per call, the batched solver a few microseconds per hypothesis.
The quartic's roots come from a vectorised Ferrari solver (:mod:`.quartic`); the pose from a
rotation between the frames spanned by the recovered camera-frame triangle and the model one.
"""

from __future__ import annotations

import numpy as np

from .quartic import quartic_roots



def p3p_batch(f: np.ndarray, X: np.ndarray, min_depth: float = 1e-6):
    """Solve P3P for H hypotheses.

    f: (H, 3, 3) unit bearings (row k = ray of point k, camera frame).
    X: (H, 3, 3) model points (row k = point k, model frame, mm).
    Returns (R, t, src): R (S, 3, 3), t (S, 3) with ``R X + t`` in the camera frame, and
    ``src`` (S,) the hypothesis index of each of the S real, positive-depth solutions.
    """
    H = f.shape[0]
    if H == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, dtype=int)
    a2 = np.sum((X[:, 1] - X[:, 2]) ** 2, axis=1)
    b2 = np.sum((X[:, 0] - X[:, 2]) ** 2, axis=1)
    c2 = np.sum((X[:, 0] - X[:, 1]) ** 2, axis=1)
    ca = np.sum(f[:, 1] * f[:, 2], axis=1)  # cos alpha: angle between rays 2, 3
    cb = np.sum(f[:, 0] * f[:, 2], axis=1)  # cos beta: rays 1, 3
    cg = np.sum(f[:, 0] * f[:, 1], axis=1)  # cos gamma: rays 1, 2
    with np.errstate(divide="ignore", invalid="ignore"):
        p = (a2 - c2) / b2
        q = (a2 + c2) / b2
        A4 = (p - 1) ** 2 - 4 * c2 / b2 * ca**2
        A3 = 4 * (p * (1 - p) * cb - (1 - q) * ca * cg + 2 * c2 / b2 * ca**2 * cb)
        A2 = 2 * (p**2 - 1 + 2 * p**2 * cb**2 + 2 * (b2 - c2) / b2 * ca**2
                  - 4 * q * ca * cb * cg + 2 * (b2 - a2) / b2 * cg**2)
        A1 = 4 * (-p * (1 + p) * cb + 2 * a2 / b2 * cg**2 * cb - (1 - q) * ca * cg)
        A0 = (1 + p) ** 2 - 4 * a2 / b2 * cg**2
    good = np.isfinite(A4) & np.isfinite(A3) & np.isfinite(A2) & np.isfinite(A1) & np.isfinite(A0) & (np.abs(A4) > 1e-14)
    roots = np.full((H, 4), np.nan + 0j)
    if good.any():
        roots[good] = quartic_roots(A4[good], A3[good], A2[good], A1[good], A0[good])
    v = roots.real
    real = np.abs(roots.imag) <= 1e-4 * np.maximum(1.0, np.abs(v))
    # u from v (Grunert's back substitution), then the distances s1, s2 = u s1, s3 = v s1.
    with np.errstate(divide="ignore", invalid="ignore"):
        pb = p[:, None]
        u = ((-1 + pb) * v**2 - 2 * pb * cb[:, None] * v + 1 + pb) / (2 * (cg[:, None] - v * ca[:, None]))
        s1sq = b2[:, None] / (1 + v**2 - 2 * v * cb[:, None])
    ok = real & np.isfinite(u) & np.isfinite(s1sq) & (s1sq > 0) & (u > 0) & (v > 0)
    hi, ri = np.nonzero(ok)
    if len(hi) == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, dtype=int)
    s1 = np.sqrt(s1sq[hi, ri])
    s = np.stack([s1, u[hi, ri] * s1, v[hi, ri] * s1], axis=1)  # (S, 3)
    P = f[hi] * s[:, :, None]  # camera-frame points (S, 3, 3)
    # Reject spurious roots (from the u back-substitution) whose side lengths do not match.
    dP = np.stack([np.sum((P[:, 1] - P[:, 2]) ** 2, 1), np.sum((P[:, 0] - P[:, 2]) ** 2, 1),
                   np.sum((P[:, 0] - P[:, 1]) ** 2, 1)], axis=1)
    dX = np.stack([a2[hi], b2[hi], c2[hi]], axis=1)
    consistent = np.all(np.abs(dP - dX) <= 1e-3 * np.maximum(dX, 1e-9), axis=1) & (P[:, :, 2].min(1) > min_depth)
    hi, P = hi[consistent], P[consistent]
    if len(hi) == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, dtype=int)
    R, t = triangle_pose(X[hi], P)
    return R, t, hi


def _frames(T: np.ndarray) -> np.ndarray:
    """Orthonormal frames (S, 3, 3) (columns e1, e2, e3) attached to triangles T (S, 3, 3)."""
    e1 = T[:, 1] - T[:, 0]
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e3 = np.cross(e1, T[:, 2] - T[:, 0])
    e3 /= np.linalg.norm(e3, axis=1, keepdims=True)
    e2 = np.cross(e3, e1)
    return np.stack([e1, e2, e3], axis=2)


def triangle_pose(X: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid (R, t) with ``R X_k + t = P_k`` for congruent triangles X, P (S, 3, 3): the rotation
    between the frames the two triangles span (exact for P3P output, ~5x cheaper than SVD)."""
    R = np.einsum("sij,skj->sik", _frames(P), _frames(X))
    cx = X.mean(axis=1)
    t = P.mean(axis=1) - np.einsum("sij,sj->si", R, cx)
    return R, t
