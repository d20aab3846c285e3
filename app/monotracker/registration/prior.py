"""Tracking fast path: reuse the previous frame's pose.

Project the fiducials with the prior ``T_cam_ct``, assign image points one-to-one inside a
motion gate (Hungarian with outlier rejection), refine by LM, re-assign with the tight gate,
refine again. The prior is considered to still explain the image when at least 4 pairs
remain, the RMS is within the acceptance gate, and no more than ``max_lost`` of the
fiducials that could be matched (min of image points and fiducials in front of the camera)
were lost; otherwise the caller falls back to the full search.
"""

from __future__ import annotations

import numpy as np

from .robust import refine_assignment

#: Image motion (equivalent px) allowed between the prior and the current frame.
PRIOR_GATE_PX = 25.0


def track_with_prior(T_prior: np.ndarray, X: np.ndarray, xn: np.ndarray, fxy: np.ndarray,
                     radius_mm: float | None, final_gate_px: float, accept_rms_px: float,
                     max_lost: int = 2):
    """Returns (pairs, refinement, why_not); refinement is None when the prior fails."""
    Xc = X @ T_prior[:3, :3].T + T_prior[:3, 3]
    if np.any(Xc[:, 2] <= 0):
        return (), None, "prior puts fiducials behind the camera"
    pairs, ref = refine_assignment(T_prior, X, xn, fxy, radius_mm,
                                   (PRIOR_GATE_PX, final_gate_px, final_gate_px))
    if ref is None:
        return pairs, None, f"prior explains only {len(pairs)} image points"
    rms = float(np.sqrt(np.mean(np.sum(ref.residuals**2, axis=1))))
    if rms > accept_rms_px:
        return pairs, None, f"prior fit RMS {rms:.1f} px over the gate"
    if len(pairs) < min(len(xn), len(X)) - max_lost:
        return pairs, None, f"prior explains {len(pairs)} of {len(xn)} image points"
    return pairs, ref, ""
