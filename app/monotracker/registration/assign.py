"""Gated one-to-one assignment of predicted to observed image points."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment


def gated_assignment(pred_px: np.ndarray, obs_px: np.ndarray, gate_px: float) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one pairs (model index array, image index array) minimising the summed squared
    distance, keeping only pairs closer than ``gate_px``. pred (n, 2), obs (m, 2), same units.

    Pairs beyond the gate get a constant cost so they never pull a good pair away (an
    assignment with outlier rejection, solved exactly by ``linear_sum_assignment``)."""
    n, m = len(pred_px), len(obs_px)
    if n == 0 or m == 0:
        return np.zeros(0, int), np.zeros(0, int)
    d2 = np.sum((pred_px[:, None, :] - obs_px[None, :, :]) ** 2, axis=2)
    g2 = gate_px * gate_px
    bad = ~(d2 <= g2)
    cost = np.where(bad, g2 * 4.0, d2)
    mi, ii = linear_sum_assignment(cost)
    keep = ~bad[mi, ii]
    return mi[keep], ii[keep]
