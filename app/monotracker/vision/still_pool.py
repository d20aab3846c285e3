"""Frames of a still head, pooled (issue 28 item 3): one pose from the mean of each fiducial's
recent detections, and the image noise measured from their scatter.

Why: one frame's centres carry sensor noise (independent from frame to frame) and a bias
(shading, a highlight, texture: the same in every frame of a still head). Averaging n frames
divides the noise's variance by n and leaves the bias; the scatter of each ball's detections
about their mean measures the noise with many degrees of freedom (2 (n - 1) per ball), so
the trust decision no longer waits for the residuals of single frames to accumulate.

Motion (choices written down):

* Each new frame is tested against the pool: the distance of its matched detections from
  their pool means, ``D = sum_j |x_j - mean_j|^2 / (sigma^2 (1 + 1 / n_j))`` (px, sigma the
  noise), is chi-square with 2m dof (m balls) when the head is still. Over its
  ``1 - alpha`` quantile (alpha 0.1 %) the head moved: the pool restarts from this frame.
  A head that moves faster than the noise can hide is therefore never averaged.
* Slower drift is bounded by ``max_frames`` (the pool spans at most that many frames, 8 =
  0.27 s at 30 fps by default): the pooled mean lags the head by half the window. At the
  threshold above the lag is at most ~1.6 sigma per ball (RMS), i.e. of the order of one
  frame's noise; :class:`PooledFit` carries the window length so that a caller can bound it.
* A frame whose registration failed, a camera fault, or a frame the caller deems unusable
  resets the pool (:meth:`StillPool.reset`).

Units: observations are undistorted normalised coordinates (x/z, y/z); distances are converted
to equivalent pinhole pixels with (fx, fy), as the registration's residuals.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from monotracker.registration.quantiles import chi2_ppf


#: the motion test's noise never below this (px): identical frames (a repeated frame, a
#: synthetic source) have no scatter, and no noise would call every new frame a motion
NOISE_FLOOR_PX = 0.02
#: degrees of freedom the caller's noise estimate is worth in the motion test
PRIOR_DOF = 10


@dataclass(frozen=True)
class PoolStats:
    """The pooled observations: ``fiducials`` (k,) indices, ``means`` (k, 2) normalised,
    ``counts`` (k,) frames per fiducial, ``frames`` in the pool, ``noise_ss_px2`` / ``noise_dof``:
    the scatter about the means (px^2, dof), ``noise_px`` = sqrt(ss / dof) (NaN without dof)."""

    fiducials: np.ndarray
    means: np.ndarray
    counts: np.ndarray
    frames: int
    noise_ss_px2: float
    noise_dof: int

    @property
    def noise_px(self) -> float:
        return float(np.sqrt(self.noise_ss_px2 / self.noise_dof)) if self.noise_dof > 0 else float("nan")


class StillPool:
    """Recent frames of a still head (see the module docstring).

    Args:
        max_frames: frames kept at most (the window; older ones drop out).
        alpha: false-alarm rate of the motion test per frame.
    """

    def __init__(self, max_frames: int = 8, alpha: float = 1e-3):
        self.max_frames = max(1, int(max_frames))
        self.alpha = float(alpha)
        self._frames: deque = deque(maxlen=self.max_frames)
        #: frames since the last restart that the motion test let in
        self.still_frames = 0

    def reset(self) -> None:
        self._frames.clear()
        self.still_frames = 0

    def __len__(self) -> int:
        return len(self._frames)

    def stats(self) -> PoolStats | None:
        """Means, counts and scatter of the pooled observations (None when empty)."""
        if not self._frames:
            return None
        fids = sorted({j for f in self._frames for j in f["obs"]})
        fxy = self._frames[-1]["fxy"]
        means, counts, ss, dof = [], [], 0.0, 0
        for j in fids:
            xs = np.array([f["obs"][j] for f in self._frames if j in f["obs"]])
            m = xs.mean(axis=0)
            means.append(m)
            counts.append(len(xs))
            ss += float(np.sum(((xs - m) * fxy) ** 2))
            dof += 2 * (len(xs) - 1)
        return PoolStats(np.array(fids, int), np.array(means), np.array(counts, int), len(self._frames), ss, dof)

    def add(self, frame_index: int, fiducials, xn: np.ndarray, fxy: np.ndarray, sigma_px: float) -> bool:
        """Add one frame's matched detections (``fiducials`` (m,) indices, ``xn`` (m, 2)
        normalised); ``sigma_px`` the caller's noise estimate (px), a prior worth ``PRIOR_DOF``
        beside the pool's own scatter in the motion test. Returns True when the frame joined a
        still pool, False when the head moved (or the pool was empty) and the pool restarted
        from this frame."""
        obs = {int(j): np.asarray(x, float) for j, x in zip(fiducials, np.asarray(xn, float).reshape(-1, 2))}
        fxy = np.asarray(fxy, float).reshape(2)
        still = False
        st = self.stats()
        if st is not None:
            # the pool's scatter with the caller's noise as a prior worth PRIOR_DOF (a scatter
            # from few frames may be low by chance: alone it would call a still head moved)
            prior = float(sigma_px) if np.isfinite(sigma_px) else float("nan")
            if np.isfinite(prior):
                sig = float(np.sqrt((st.noise_ss_px2 + PRIOR_DOF * prior**2) / (st.noise_dof + PRIOR_DOF)))
            else:
                sig = st.noise_px if st.noise_dof > 0 else NOISE_FLOOR_PX
            sig = max(sig, NOISE_FLOOR_PX) if np.isfinite(sig) else NOISE_FLOOR_PX
            common = [(k, j) for k, j in enumerate(st.fiducials) if j in obs]
            if common:
                d2 = sum(float(np.sum(((obs[j] - st.means[k]) * fxy) ** 2)) / (1.0 + 1.0 / st.counts[k])
                         for k, j in common) / sig**2
                still = d2 <= chi2_ppf(1.0 - self.alpha, 2 * len(common))
        if not still:
            self._frames.clear()
            self.still_frames = 0
        self._frames.append({"index": int(frame_index), "obs": obs, "fxy": fxy})
        self.still_frames += 1
        return bool(still)
