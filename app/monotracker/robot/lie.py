"""SE(3) / so(3) helpers for the robot side (metres, radians).

Conventions (Lynch & Park, "Modern Robotics", the paper's POE formulation):

* A twist is ``V = (omega, v)`` (6,): angular part first, then linear, in rad/s and m/s.
* A wrench is ``F = (m, f)`` (6,): moment (N m) first, then force (N).
* ``adjoint(T)`` maps twists expressed in frame b to frame a for ``T = T_a_b``;
  wrenches map with the transpose: ``F_b = adjoint(T_a_b).T @ F_a``.
* ``exp6(xi)`` is the matrix exponential of a twist (4,4); ``log6(T)`` its inverse.

Two implementations of the same maps: ``exp6_ref``/``log6_ref``/``adjoint_ref`` write the
formulas out in numpy (used by the paper's POE model and as the reference in the tests);
``exp6``/``log6``/``adjoint``/``inverse`` call pinocchio's C++ (about 20x faster, the control
loop's hot path) and reorder pinocchio's ``(v, omega)`` to our ``(omega, v)``.
"""

from __future__ import annotations

import numpy as np


def hat(w: np.ndarray) -> np.ndarray:
    """3x3 skew-symmetric matrix of ``w`` (3,): ``hat(w) @ x == cross(w, x)``."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def exp3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix ``exp(hat(w))`` for a rotation vector ``w`` (rad)."""
    th = float(np.linalg.norm(w))
    K = hat(w)
    if th < 1e-9:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / th**2 * (K @ K)


def log3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad, (3,)) of a rotation matrix; angle in [0, pi]."""
    c = np.clip((np.trace(R) - 1.0) * 0.5, -1.0, 1.0)
    th = float(np.arccos(c))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-6:
        return 0.5 * v * (1.0 + th**2 / 6.0)
    if np.pi - th < 1e-4:
        # Near pi: axis from the symmetric part, sign fixed by the small skew part.
        B = 0.5 * (R + np.eye(3))
        k = int(np.argmax(np.diag(B)))
        axis = B[:, k] / np.sqrt(max(B[k, k], 1e-12))
        if np.dot(axis, v) < 0:
            axis = -axis
        return th * axis / np.linalg.norm(axis)
    return th / (2.0 * np.sin(th)) * v


def exp6_ref(xi: np.ndarray) -> np.ndarray:
    """4x4 transform ``exp([xi])`` (numpy reference) of a twist ``xi = (omega, v)`` (unit-time displacement)."""
    w = np.asarray(xi[:3], dtype=float)
    v = np.asarray(xi[3:], dtype=float)
    th = float(np.linalg.norm(w))
    T = np.eye(4)
    K = hat(w)
    if th < 1e-9:
        T[:3, :3] = np.eye(3) + K
        T[:3, 3] = v + 0.5 * K @ v
        return T
    T[:3, :3] = exp3(w)
    G = np.eye(3) + (1.0 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * (K @ K)
    T[:3, 3] = G @ v
    return T


def log6_ref(T: np.ndarray) -> np.ndarray:
    """Twist ``xi = (omega, v)`` (6,) with ``exp6_ref(xi) == T``."""
    R = T[:3, :3]
    p = T[:3, 3]
    w = log3(R)
    th = float(np.linalg.norm(w))
    K = hat(w)
    if th < 1e-9:
        return np.concatenate([w, p - 0.5 * K @ p])
    # Inverse of the left Jacobian G(w).
    Ginv = np.eye(3) - 0.5 * K + (1.0 / th**2) * (1.0 - (th / 2.0) / np.tan(th / 2.0)) * (K @ K)
    return np.concatenate([w, Ginv @ p])


def adjoint_ref(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of ``T = T_a_b``: twists in b -> twists in a (``(omega, v)`` order)."""
    R = T[:3, :3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = hat(T[:3, 3]) @ R
    return A



# ----------------------------------------------------------------------------- fast path
import pinocchio as _pin  # noqa: E402

_P = np.array([3, 4, 5, 0, 1, 2])


def exp6(xi: np.ndarray) -> np.ndarray:
    """Same as :func:`exp6_ref` (pinocchio)."""
    return _pin.exp6(np.asarray(xi, dtype=float)[_P]).homogeneous


def log6(T: np.ndarray) -> np.ndarray:
    """Same as :func:`log6_ref` (pinocchio)."""
    return _pin.log6(np.asarray(T, dtype=float)).vector[_P]


def adjoint(T: np.ndarray) -> np.ndarray:
    """Same as :func:`adjoint_ref` (pinocchio)."""
    A = _pin.SE3(np.asarray(T, dtype=float)).toActionMatrix()
    out = np.empty((6, 6))
    out[:3, :3] = A[3:, 3:]
    out[:3, 3:] = A[3:, :3]
    out[3:, :3] = A[:3, 3:]
    out[3:, 3:] = A[:3, :3]
    return out


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform; equals ``geometry.invert_transform`` (fast path)."""
    return _pin.SE3(T).inverse().homogeneous


def relative(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A^-1 @ B`` for rigid transforms (fast path)."""
    return _pin.SE3(A).actInv(_pin.SE3(B)).homogeneous
