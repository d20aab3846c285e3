"""Least-squares rigid fit (Kabsch / Umeyama without scale), single and batched."""

from __future__ import annotations

import numpy as np


def kabsch_batch(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations R (H, 3, 3) and translations t (H, 3) minimising sum ||R a + t - b||^2 for
    each batch of corresponding points A, B (H, k, 3). Reflections are excluded."""
    ca = A.mean(axis=1, keepdims=True)
    cb = B.mean(axis=1, keepdims=True)
    H = np.einsum("hki,hkj->hij", A - ca, B - cb)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("hij,hjk->hik", U, Vt)))
    D = np.zeros_like(H)
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.where(d == 0, 1.0, d)
    R = np.einsum("hji,hjk,hlk->hil", Vt, D, U)  # V D U^T
    t = cb[:, 0, :] - np.einsum("hij,hj->hi", R, ca[:, 0, :])
    return R, t


def kabsch(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """4x4 ``T_b_a`` with ``T_b_a @ a ~= b`` for corresponding (k, 3) point sets A, B."""
    R, t = kabsch_batch(np.asarray(A, float)[None], np.asarray(B, float)[None])
    T = np.eye(4)
    T[:3, :3] = R[0]
    T[:3, 3] = t[0]
    return T
