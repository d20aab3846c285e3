"""One check for "is this a rigid transform", shared by every way a pose enters: the robot's
safety layer (targets), hand-eye calibration (input poses) and the engine's plan checks
(``T_base_cam``). Each caller keeps its own tolerance (a target that went through unit
conversions and a hand-typed calibration are held to different standards) and its own wording
around the reason. Any units (only the rotation block and the last row are judged)."""

from __future__ import annotations

import numpy as np


def rigid_problem(T, tol: float, name: str = "the transform") -> str | None:
    """None when ``T`` is a finite 4x4 rigid transform: ``R^T R = I`` (max abs deviation) and
    ``det R = +1`` within ``tol``, last row ``(0, 0, 0, 1)``; otherwise one line saying what is
    wrong, starting with ``name``. Never raises."""
    try:
        a = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        return f"{name} is not a 4x4 array of numbers"
    if a.shape != (4, 4):
        return f"{name} must be 4x4, not {'x'.join(map(str, a.shape)) or 'a scalar'}"
    if not np.all(np.isfinite(a)):
        return f"{name} has non-finite entries (NaN or inf)"
    R = a[:3, :3]
    with np.errstate(all="ignore"):  # huge entries overflow to inf: refused below
        orth = float(np.abs(R.T @ R - np.eye(3)).max())
        det = float(np.linalg.det(R))
    if not (np.isfinite(orth) and np.isfinite(det)):
        return f"{name} is not a rigid transform (its entries are far too large)"
    if det < 0:
        return f"{name} is a reflection (det {det:.3f}), not a rigid transform"
    if orth > tol or abs(det - 1.0) > tol:
        return f"{name} is not a rigid transform (|R^T R - I| {orth:.2g}, det {det:.4f})"
    if not np.allclose(a[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
        return f"{name}'s last row must be (0, 0, 0, 1)"
    return None
