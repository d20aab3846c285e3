"""The running mean of a still camera view's frames, for the detector (issue 28, opt-in).

A dim, noisy camera (60 % light, a small sensor's full well, JPEG) loses whole balls to its own
noise: the colour mask's boundary frays and the edge rays' unmixing fails ("boundary not
elliptic", "too little contrast"). While nothing in the view moves, the mean of the last frames
has the same balls with the noise of one frame divided by sqrt(n); the detector then reads the
mean instead of the frame (:attr:`~.pose_tracker.TrackerConfig.average_still_frames`).

The mean is only kept while the view is still at the precision a centre needs. Each new frame is
compared with the mean before it joins it (grey levels, DN):

* **a ball moved**: in a window around each ball the last detection found (accepted or refused),
  the new frame minus the mean is fitted as the mean's gradient times a shift (px) plus an
  offset (Lucas-Kanade, one step). A shift that a still view gives with probability under
  ``shift_false_alarm`` in any ball, or a motion of the balls together (their shifts fitted as
  one 2D similarity: a head moving, turning, coming closer) as unlikely, starts the mean again
  from this frame;
* **something changed in a ball's window** (a finger or an instrument coming in, a lamp on the
  ball): the fit's mean squared residual over ``residual_ratio`` x the difference noise's;
* **something changed anywhere**: in any 64 px tile, more than ``changed_share`` of the
  (4x subsampled) pixels differ from the mean by over ``change_sigmas`` x the difference noise.

The difference noise is measured in each frame: the robust spread of the difference in bins of
the mean's grey level (shot noise grows with the light), the shift fits weighted by it.

A moving head therefore gets single frames, as without the mean; a head drifting slower than the
tests see (under ~0.05 px for the balls together since the mean started) gets a mean that lags
it by up to ``max_frames / 2`` frames. The mean weighs the frames equally up to ``max_frames``,
then exponentially (weight ``1 / max_frames`` for the newest).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

#: frames averaged at most (8 = 0.27 s at 30 fps, the pose pool's span)
MAX_FRAMES = 8
#: a ball's shift between the new frame and the mean starts the mean again when a still view
#: would give one as large with this probability or less (Hotelling's T^2 of the shift against
#: its covariance summed over the window's blocks: a covariance from few blocks is itself
#: uncertain; ~5.5 standard deviations with 49 blocks, ~7.9 with 16)
SHIFT_FALSE_ALARM = 1e-5
#: ball windows tested at most (the detection's accepted balls first)
MAX_WINDOWS = 40
#: a ball window's fit residual (mean square, in units of the difference noise's variance) over
#: this: something changed there (still frames: 0.9-2.6 on the rendered tuning sets, JPEG's
#: ringing at the balls' edges above 1)
RESIDUAL_RATIO = 4.0
#: a pixel differs when over this many robust standard deviations of the frame's difference
CHANGE_SIGMAS = 5.0
#: ... and a tile changed when more than this share of its (subsampled) pixels differ
CHANGED_SHARE = 0.02
TILE_PX = 64
SUBSAMPLE = 4
#: ball windows: the ball's radius plus this margin (px; the edge and its blur)
WINDOW_MARGIN_PX = 4.0
#: the difference noise is at least this (DN: 8-bit quantisation) ...
MIN_NOISE_DN = 0.5
#: ... and measured in this many bins of grey level, each of at least this many pixels
NOISE_BINS = 16
NOISE_BIN_MIN = 50
#: ... from a histogram of |difference| in steps of this (DN) up to NOISE_STEPS steps
NOISE_STEP_DN = 0.25
NOISE_STEPS = 256
TRIM_QUANTILE = 0.98
#: a Gaussian's RMS within its central 98 % (|z| <= 2.326) per sigma
TRIMMED_RMS_PER_SIGMA = 0.934
#: the shift's covariance is summed over blocks of this many px square (the sensor chain's
#: noise is correlated over a few px: lens blur before the noise, demosaicing, JPEG's 8 px
#: blocks; per pixel the shift's spread reads 2x too small on JPEG frames)
BLOCK_PX = 4
#: the balls' shifts together fitted as a 2D similarity (shift, rotation, scale; 4 parameters)
#: or, with fewer than 3 balls, a common shift (2): chi-square over these (false alarm 1e-5 for
#: Gaussian estimates) starts the mean again
MOTION_CHI2_4 = 25.45
MOTION_CHI2_2 = 23.03


class StillFrames:
    """The running mean of the frames since the view last moved (BGR, float32) and the test
    that decides whether a new frame joins it. :meth:`add` returns the image to detect on (the
    mean, uint8) and :attr:`n` the frames in it; :attr:`last_reason` why the last frame started
    the mean again ("" when it joined)."""

    def __init__(self, max_frames: int = MAX_FRAMES, shift_false_alarm: float = SHIFT_FALSE_ALARM,
                 residual_ratio: float = RESIDUAL_RATIO, change_sigmas: float = CHANGE_SIGMAS,
                 changed_share: float = CHANGED_SHARE):
        if int(max_frames) < 1:
            raise ValueError(f"max_frames must be at least 1, got {max_frames!r}")
        self.max_frames = int(max_frames)
        self.shift_false_alarm = float(shift_false_alarm)
        self.residual_ratio = float(residual_ratio)
        self.change_sigmas = float(change_sigmas)
        self.changed_share = float(changed_share)
        self.reset()

    def reset(self) -> None:
        """Forget the mean (the next frame starts it)."""
        self._mean: np.ndarray | None = None
        self._grey: np.ndarray | None = None
        self.n = 0
        self.last_reason = "first frame"

    def add(self, image: np.ndarray, balls_px: np.ndarray) -> np.ndarray:
        """Join ``image`` (BGR uint8) to the mean if the view is still, else start the mean
        with it; the image to detect on (uint8, ``image`` itself when the mean holds one frame).
        ``balls_px``: (m, 3) float, the balls' centres and radii (px) that the last detection
        found, accepted or refused (the windows whose shift is tested; may be empty)."""
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float32)
        if self._mean is None or self._mean.shape != image.shape:
            return self._start(image, grey, "first frame" if self._mean is None else "frame size changed")
        why = self.moved(grey, np.asarray(balls_px, float).reshape(-1, 3))
        if why:
            return self._start(image, grey, why)
        self.n += 1
        alpha = 1.0 / min(self.n, self.max_frames)
        cv2.accumulateWeighted(image, self._mean, alpha)
        cv2.accumulateWeighted(grey, self._grey, alpha)
        self.last_reason = ""
        return cv2.convertScaleAbs(self._mean)

    def _start(self, image: np.ndarray, grey: np.ndarray, why: str) -> np.ndarray:
        self._mean = image.astype(np.float32)
        self._grey = grey
        self.n = 1
        self.last_reason = why
        return image

    def moved(self, grey: np.ndarray, balls_px: np.ndarray) -> str:
        """Why ``grey`` (float32 DN) does not join the mean ("" = it does; see the module
        docstring)."""
        diff = grey - self._grey
        H, W = grey.shape
        sub = diff[::SUBSAMPLE, ::SUBSAMPLE]
        med = float(np.median(sub[::2, ::2]))
        noise_of = self._noise_model(self._grey[::SUBSAMPLE, ::SUBSAMPLE], sub - med)
        # the balls first: a moving head fails here, at its first window
        shifts, infos, where = [], [], []
        for cx, cy, r in balls_px[:MAX_WINDOWS]:
            if not (np.isfinite(cx) and np.isfinite(cy) and np.isfinite(r)):
                continue
            g = r + WINDOW_MARGIN_PX
            x0, x1 = max(int(cx - g), 1), min(int(np.ceil(cx + g)) + 1, W - 1)
            y0, y1 = max(int(cy - g), 1), min(int(np.ceil(cy + g)) + 1, H - 1)
            if x1 - x0 < 2 * BLOCK_PX or y1 - y0 < 2 * BLOCK_PX:
                continue
            fit = _window_shift(self._grey[y0 - 1:y1 + 1, x0 - 1:x1 + 1], diff[y0:y1, x0:x1] - med, noise_of)
            if fit is None:
                continue
            shift, cov, resid_ratio, blocks = fit
            if resid_ratio > self.residual_ratio:
                return f"a ball's window changed at ({cx:.0f}, {cy:.0f}) px"
            info = np.linalg.inv(cov)
            if float(shift @ info @ shift) > _shift_limit2(blocks, self.shift_false_alarm):
                return f"a ball moved {float(np.hypot(*shift)):.2f} px at ({cx:.0f}, {cy:.0f}) px"
            shifts.append(shift)
            infos.append(info)
            where.append((cx, cy))
        if shifts:
            chi2, moved_px = _common_motion(np.array(where), np.array(shifts), np.array(infos))
            if chi2 > (MOTION_CHI2_4 if len(shifts) >= 3 else MOTION_CHI2_2):
                return f"the balls moved together (up to {moved_px:.2f} px)"
        # then the whole view, in 4 x 4 px block means (a demosaic's single-pixel flips average out)
        small = (max(W // SUBSAMPLE, 1), max(H // SUBSAMPLE, 1))
        blocks_diff = cv2.resize(diff, small, interpolation=cv2.INTER_AREA) - med
        level = cv2.resize(self._grey, small, interpolation=cv2.INTER_AREA)
        big = np.abs(blocks_diff) > self.change_sigmas * self._noise_model(level, blocks_diff)(level)
        t = TILE_PX // SUBSAMPLE
        h, w = (big.shape[0] // t) * t, (big.shape[1] // t) * t
        if h and w:
            share = big[:h, :w].reshape(h // t, t, w // t, t).mean(axis=(1, 3))
            if float(share.max()) > self.changed_share:
                return f"{100 * float(share.max()):.0f} % of a tile changed"
        return ""

    @staticmethod
    def _noise_model(level: np.ndarray, diff: np.ndarray):
        """sigma(grey level) of the difference ``diff`` (DN) between a frame and the mean, from
        its spread in bins of the mean's grey ``level`` (a sensor's noise grows with the light:
        shot noise): the RMS of the bin's central 98 % (a few changed pixels do not count; a
        median would read the 8-bit steps of a quiet sensor's difference as no noise at all),
        as a Gaussian's sigma; a function of a level array (float32 DN, at least
        :data:`MIN_NOISE_DN`)."""
        lv = np.clip((level.ravel() * (NOISE_BINS / 256.0)).astype(np.int32), 0, NOISE_BINS - 1)
        ad = np.minimum((np.abs(diff.ravel()) * (1.0 / NOISE_STEP_DN)).astype(np.int32), NOISE_STEPS - 1)
        hist = np.bincount(lv * NOISE_STEPS + ad, minlength=NOISE_BINS * NOISE_STEPS).reshape(NOISE_BINS, NOISE_STEPS)
        mid2 = ((np.arange(NOISE_STEPS) + 0.5) * NOISE_STEP_DN) ** 2
        centres, sig = [], []
        for b in np.flatnonzero(hist.sum(axis=1) >= NOISE_BIN_MIN):
            h = hist[b]
            keep = np.cumsum(h) <= TRIM_QUANTILE * h.sum()     # the central 98 % of |diff|
            keep[0] = True
            rms = float(np.sqrt((h[keep] * mid2[keep]).sum() / max(h[keep].sum(), 1)))
            centres.append((b + 0.5) * 256.0 / NOISE_BINS)
            sig.append(max(rms / TRIMMED_RMS_PER_SIGMA, MIN_NOISE_DN))
        if not centres:
            return lambda lv: np.full(np.shape(lv), MIN_NOISE_DN, np.float32)
        c, s_ = np.array(centres), np.array(sig)
        return lambda lv: np.interp(lv, c, s_).astype(np.float32)


def _window_shift(mean_pad: np.ndarray, diff: np.ndarray, noise_of):
    """One Lucas-Kanade step in a ball's window: ``diff`` (h, w; the new frame minus the mean,
    DN) = the mean's gradient x shift + offset, each pixel weighted by 1 / its noise
    (``noise_of``). ``mean_pad``: the mean's grey over the window and a 1 px border. (shift (2,)
    px, its covariance (2, 2) px^2 summed over :data:`BLOCK_PX` blocks of the residuals'
    scores (noise correlated over a few px), the residual's mean square per noise variance, the
    number of blocks), or None where the window has no gradient."""
    m = mean_pad
    gx = 0.5 * (m[1:-1, 2:] - m[1:-1, :-2])
    gy = 0.5 * (m[2:, 1:-1] - m[:-2, 1:-1])
    wt = 1.0 / noise_of(m[1:-1, 1:-1]).astype(np.float64)
    A = np.stack([gx * wt, gy * wt, wt], axis=-1)
    d = diff * wt
    Af, df = A.reshape(-1, 3), d.ravel()
    N = Af.T @ Af
    if not np.linalg.cond(N) < 1e8:
        return None
    Ninv = np.linalg.inv(N)
    p = Ninv @ (Af.T @ df)
    res = (df - Af @ p).reshape(d.shape)
    ratio = float(np.mean(res * res)) * df.size / max(df.size - 3, 1)
    sc = A * res[..., None]
    h, w = (sc.shape[0] // BLOCK_PX) * BLOCK_PX, (sc.shape[1] // BLOCK_PX) * BLOCK_PX
    S = sc[:h, :w].reshape(h // BLOCK_PX, BLOCK_PX, w // BLOCK_PX, BLOCK_PX, 3).sum(axis=(1, 3)).reshape(-1, 3)
    k = len(S)
    cov = (Ninv @ (S.T @ S) @ Ninv)[:2, :2] * (k / (k - 1.0))
    if not (np.all(np.isfinite(cov)) and np.linalg.det(cov) > 0):
        return None
    return p[:2], cov, ratio, k


@lru_cache(maxsize=256)
def _shift_limit2(blocks: int, false_alarm: float) -> float:
    """The squared Mahalanobis length of a 2D shift that a still view exceeds with probability
    ``false_alarm`` when its covariance is estimated from ``blocks`` blocks (Hotelling's T^2:
    2 (k - 1) / (k - 2) F(2, k - 2))."""
    from scipy.stats import f

    k = max(int(blocks), 4)
    return float(2.0 * (k - 1) / (k - 2) * f.isf(false_alarm, 2, k - 2))


def _common_motion(where: np.ndarray, shifts: np.ndarray, infos: np.ndarray) -> tuple[float, float]:
    """The balls' shifts (m, 2) px at ``where`` (m, 2) px, each with its information matrix
    (m, 2, 2), fitted as one 2D similarity about their centroid (shift, rotation, scale) or, with
    fewer than 3 balls, one shift: (its chi-square against no motion, the largest shift it gives
    a ball, px)."""
    c = where.mean(axis=0)
    x, y = where[:, 0] - c[0], where[:, 1] - c[1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    if len(where) >= 3:
        J = np.stack([np.stack([one, zero, x, -y], axis=1), np.stack([zero, one, y, x], axis=1)], axis=1)
    else:
        J = np.stack([np.stack([one, zero], axis=1), np.stack([zero, one], axis=1)], axis=1)
    F = np.einsum("mki,mkl,mlj->ij", J, infos, J)
    g = np.einsum("mki,mkl,ml->i", J, infos, shifts)
    try:
        theta = np.linalg.solve(F, g)
    except np.linalg.LinAlgError:
        return 0.0, 0.0
    moved = np.einsum("mki,i->mk", J, theta)
    return float(theta @ F @ theta), float(np.hypot(moved[:, 0], moved[:, 1]).max())
