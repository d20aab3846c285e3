"""A test helper shared by test_shading_check and test_pose_trust_shading: the centre bias that
changes linearly across a layout and moves the refitted target most."""

from __future__ import annotations

import numpy as np

from monotracker.registration.report import layout_units


def worst_layout_field(px: np.ndarray, target_of, step_px: float = 0.01) -> np.ndarray:
    """The per-ball image shifts (k, 2) px ``G u_i`` (``u_i`` the balls' layout units,
    :func:`~monotracker.registration.report.layout_units` of their centres ``px``; ``G`` a 2 x 2
    matrix of unit Frobenius norm) that move the target most to first order: ``target_of(shifts)``
    is the target (camera frame, mm, (3,)) under the pose refitted to ``px + shifts``; finite
    differences of ``step_px`` over the four entries of ``G``, the top eigenvector of D^T D."""
    u = layout_units(px)
    t0 = target_of(np.zeros_like(px))
    basis = [u @ np.eye(2)[[a]].T @ np.eye(2)[[b]] for a in range(2) for b in range(2)]   # G = e_b e_a^T
    D = np.array([(target_of(step_px * B) - t0) / step_px for B in basis]).T              # (3, 4) mm per px
    g = np.linalg.eigh(D.T @ D)[1][:, -1]
    return sum(gi * B for gi, B in zip(g, basis))
