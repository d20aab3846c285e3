"""The running mean of a still camera view's frames, for the detector (issue 28, opt-in).

A dim, noisy camera (60 % light, a small sensor's full well, JPEG) loses whole balls to its own
noise: the colour mask's boundary frays and the edge rays' unmixing fails ("boundary not
elliptic", "too little contrast"). While nothing in the view moves, the mean of the last frames
has the same balls with the noise of one frame divided by sqrt(n); the detector then reads the
mean instead of the frame (:attr:`~.tracker_config.TrackerConfig.average_still_frames`).

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
* **something changed anywhere**: in any 64 px tile (or, while the detector reads only its
  search windows, in any of them), more than ``changed_share`` of the 4 x 4 px block means
  differ from the mean's by over ``change_sigmas`` x their difference noise.

The difference noise is measured in each frame: the robust spread of the difference in bins of
the mean's grey level (shot noise grows with the light): in the balls' windows for the shift
fits (each pixel weighted by it), in the block means for the change test; each after removing
the median difference (a lamp's or the exposure's small common change).

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
#: OpenCV's grey from BGR (cv2.COLOR_BGR2GRAY)
GREY_BGR = np.array([0.114, 0.587, 0.299], np.float32)
GREY_ROW = GREY_BGR.reshape(1, 3)   # the same for cv2.transform
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
#: search windows narrower than this (px) are not kept in the mean
TILE_MIN_PX = 8
#: ball windows: the ball's radius plus this margin (px; the edge and its blur)
WINDOW_MARGIN_PX = 4.0
#: the difference noise is at least this (DN: 8-bit quantisation) ...
MIN_NOISE_DN = 0.5
#: ... and measured in this many bins of grey level, each of at least this many pixels (of every
#: second subsampled pixel)
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
    the mean again ("" when it joined).

    ``min_noise_dn``: the mean is given to the detector only while the camera's noise per frame
    (:attr:`noise_dn`: grey levels, 8-bit DN, measured in the balls' windows from a joining
    frame's difference to the mean) is at least this; below it the frame itself is given (the
    mean is still kept and tested, so it is there as soon as the noise rises). 0: always.
    :attr:`giving`: whether the last :meth:`add` gave the mean."""

    def __init__(self, max_frames: int = MAX_FRAMES, shift_false_alarm: float = SHIFT_FALSE_ALARM,
                 residual_ratio: float = RESIDUAL_RATIO, change_sigmas: float = CHANGE_SIGMAS,
                 changed_share: float = CHANGED_SHARE, min_noise_dn: float = 0.0):
        if int(max_frames) < 1:
            raise ValueError(f"max_frames must be at least 1, got {max_frames!r}")
        if not (float(min_noise_dn) >= 0.0):
            raise ValueError(f"min_noise_dn must be a number of grey levels >= 0, got {min_noise_dn!r}")
        self.min_noise_dn = float(min_noise_dn)
        self.max_frames = int(max_frames)
        self.shift_false_alarm = float(shift_false_alarm)
        self.residual_ratio = float(residual_ratio)
        self.change_sigmas = float(change_sigmas)
        self.changed_share = float(changed_share)
        self.reset()

    def reset(self) -> None:
        """Forget the mean (the next frame starts it)."""
        self._mean: np.ndarray | None = None     # (H, W, 3) float32 BGR
        self._blocks: np.ndarray | None = None   # the mean's grey in SUBSAMPLE x SUBSAMPLE block means
        self._partial = False                    # kept in the detector's boxes only since the last whole read
        self.noise_dn: float | None = None       # the camera's noise per frame (DN), last measured
        self.giving = False
        self.n = 0
        self.last_reason = "first frame"

    def add(self, image: np.ndarray, balls_px: np.ndarray, region: list | None = None) -> np.ndarray:
        """Join ``image`` (BGR uint8) to the mean if the view is still, else start the mean
        with it; the image to detect on (uint8, ``image`` itself when the mean holds one frame).
        ``balls_px``: (m, 3) float, the balls' centres and radii (px) that the last detection
        found, accepted or refused (the windows whose shift is tested; may be empty).
        ``region``: None (the detector reads the whole frame) or the boxes (x0, y0, x1, y1) px
        that it reads (its search windows while the balls are tracked): the mean is then kept,
        tested and given only there, at a fraction of the cost (the returned image is the frame
        elsewhere), and the whole view is judged again at the next whole-frame read."""
        if self._mean is None or self._mean.shape != image.shape:
            return self._start(image, cv2.cvtColor(image, cv2.COLOR_BGR2GRAY),
                               "first frame" if self._mean is None else "frame size changed")
        balls = np.asarray(balls_px, float).reshape(-1, 3)
        if region is not None:
            return self._add_in(image, balls, [tuple(int(v) for v in b) for b in region])
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        if self._partial:      # kept in boxes only since: its grey block means follow it again
            self._blocks = cv2.resize(cv2.transform(self._mean, GREY_ROW), self._blocks.shape[::-1],
                                      interpolation=cv2.INTER_AREA)
            self._partial = False
        why, blocks, noise = self._moved(image, grey, balls)
        if why:
            return self._start(image, grey, why, blocks)
        self._joined(noise)
        alpha = 1.0 / min(self.n, self.max_frames)
        cv2.accumulateWeighted(image, self._mean, alpha)
        cv2.accumulateWeighted(blocks, self._blocks, alpha)
        self.last_reason = ""
        return cv2.convertScaleAbs(self._mean) if self.giving else image

    def _add_in(self, image: np.ndarray, balls: np.ndarray, boxes: list) -> np.ndarray:
        """:meth:`add` for a detector that reads only ``boxes``: the same tests of the balls'
        windows, the tile test in each box, the mean kept there (the frame's grey is only
        computed there)."""
        H, W = image.shape[:2]
        boxes = [(max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)) for x0, y0, x1, y1 in boxes]
        boxes = [b for b in boxes if b[2] - b[0] >= TILE_MIN_PX and b[3] - b[1] >= TILE_MIN_PX]
        if not boxes:
            self.giving = False
            return image
        means = [self._mean[y0:y1, x0:x1] for x0, y0, x1, y1 in boxes]
        why, noise = self._balls_moved(image, balls)
        if not why:      # then each box, in block means (the frame's grey only computed there)
            levels, blocks = [], []
            for (x0, y0, x1, y1), m in zip(boxes, means):
                size = (max((x1 - x0) // SUBSAMPLE, 1), max((y1 - y0) // SUBSAMPLE, 1))
                levels.append(cv2.transform(cv2.resize(m, size, interpolation=cv2.INTER_AREA), GREY_ROW).ravel())
                d = cv2.subtract(image[y0:y1, x0:x1], m, dtype=cv2.CV_32F)
                blocks.append(cv2.transform(cv2.resize(d, size, interpolation=cv2.INTER_AREA), GREY_ROW).ravel())
            flat_blocks = np.concatenate(blocks)
            flat_blocks -= np.float32(_median(flat_blocks))
            flat_levels = np.concatenate(levels)
            big = np.abs(flat_blocks) > self.change_sigmas * self._noise_model(flat_levels, flat_blocks)(flat_levels)
            sizes = np.array([b.size for b in blocks])
            shares = np.add.reduceat(big, np.cumsum(sizes) - sizes) / sizes      # per box
            worst = int(np.argmax(shares))
            if float(shares[worst]) > self.changed_share:
                why = (f"{100 * float(shares[worst]):.0f} % of the search window at "
                       f"({boxes[worst][0]}, {boxes[worst][1]}) px changed")
        if why:
            return self._start(image, None, why, boxes=boxes)
        self._joined(noise)
        self._partial = True
        alpha = 1.0 / min(self.n, self.max_frames)
        out = image.copy() if self.giving else image
        for (x0, y0, x1, y1), m in zip(boxes, means):
            cv2.accumulateWeighted(image[y0:y1, x0:x1], m, alpha)
            if self.giving:
                out[y0:y1, x0:x1] = cv2.convertScaleAbs(m)
        self.last_reason = ""
        return out

    def _joined(self, diff_noise: float | None) -> None:
        """A frame joins the mean: count it, update :attr:`noise_dn` from ``diff_noise`` (DN, the
        median noise of its difference to the mean of the ``m`` frames before it in the balls'
        windows, variance sigma^2 (1 + 1/m); None without windows), decide :attr:`giving`."""
        m = min(self.n, self.max_frames)
        self.n += 1
        if diff_noise is not None:
            self.noise_dn = float(diff_noise) / float(np.sqrt(1.0 + 1.0 / m))
        self.giving = self.min_noise_dn <= 0.0 or (self.noise_dn is not None and self.noise_dn >= self.min_noise_dn)

    def _start(self, image: np.ndarray, grey: np.ndarray | None, why: str, blocks=None, boxes=None) -> np.ndarray:
        if boxes is not None and self._mean is not None and self._mean.shape == image.shape:
            # the detector reads these boxes only: the mean starts there (the rest is judged at
            # the next whole-frame read, against what the mean held there)
            for x0, y0, x1, y1 in boxes:
                self._mean[y0:y1, x0:x1] = image[y0:y1, x0:x1]
            self._partial = True
            self.n = 1
            self.giving = False
            self.last_reason = why
            return image
        if self._mean is None or self._mean.shape != image.shape:
            self._mean = np.empty(image.shape, np.float32)
        np.copyto(self._mean, image, casting="unsafe")
        self._blocks = _block_means(grey) if blocks is None else blocks
        self._partial = False
        self.n = 1
        self.giving = False
        self.last_reason = why
        return image

    def _moved(self, image: np.ndarray, grey: np.ndarray, balls_px: np.ndarray) -> tuple:
        """(why ``image`` (BGR uint8; ``grey`` its grey) does not join the mean, "" if it does;
        its block means when they were computed, else None; the balls' windows' difference noise
        (DN) or None)."""
        why, noise = self._balls_moved(image, balls_px)
        if why:
            return why, None, noise
        # then the whole view, in block means (a demosaic's single-pixel flips average out)
        blocks = _block_means(grey)
        blocks_diff = blocks - self._blocks
        blocks_diff -= np.float32(_median(blocks_diff[::2, ::2].ravel()))
        big = np.abs(blocks_diff) > self.change_sigmas * self._noise_model(self._blocks, blocks_diff)(self._blocks)
        t = TILE_PX // SUBSAMPLE
        h, w = (big.shape[0] // t) * t, (big.shape[1] // t) * t
        if h and w:
            share = big[:h, :w].reshape(h // t, t, w // t, t).mean(axis=(1, 3))
            if float(share.max()) > self.changed_share:
                return f"{100 * float(share.max()):.0f} % of a tile changed", blocks, noise
        return "", blocks, noise

    def _balls_moved(self, image: np.ndarray, balls_px: np.ndarray) -> tuple[str, float | None]:
        """The tests of the balls' windows in ``image`` (BGR uint8; see the module docstring):
        (why they fail (the first ball in the windows' order that fails) or "", the windows'
        median difference noise (DN), None without windows)."""
        fits = _window_fits(self._mean, image, balls_px, self._noise_model)
        if fits is None:
            return "", None
        where, shifts, covs, ratios, nblocks, noise = fits
        infos = np.linalg.inv(covs)
        t2 = np.einsum("ni,nij,nj->n", shifts, infos, shifts)
        changed = ratios > self.residual_ratio
        moved = t2 > _shift_limit2(nblocks, self.shift_false_alarm)
        if changed.any() or moved.any():
            i = int(np.argmax(changed | moved))
            cx, cy = where[i]
            if changed[i]:
                return f"a ball's window changed at ({cx:.0f}, {cy:.0f}) px", noise
            return f"a ball moved {float(np.hypot(*shifts[i])):.2f} px at ({cx:.0f}, {cy:.0f}) px", noise
        chi2, moved_px = _common_motion(where, shifts, infos)
        if chi2 > (MOTION_CHI2_4 if len(shifts) >= 3 else MOTION_CHI2_2):
            return f"the balls moved together (up to {moved_px:.2f} px)", noise
        return "", noise

    @staticmethod
    def _noise_model(level: np.ndarray, diff: np.ndarray, step: bool = True):
        """sigma(grey level) of the difference ``diff`` (DN) between a frame and the mean, from
        its spread in bins of the mean's grey ``level`` (a sensor's noise grows with the light:
        shot noise): the RMS of the bin's central 98 % (a few changed pixels do not count; a
        median would read the 8-bit steps of a quiet sensor's difference as no noise at all),
        as a Gaussian's sigma; a function of a level array (float32 DN, at least
        :data:`MIN_NOISE_DN`). ``step``: from a quarter of the values only."""
        if step:      # a quarter of a frame's or a box's blocks measures it well enough
            level, diff = (level[::2, ::2], diff[::2, ::2]) if level.ndim == 2 else (level[::4], diff[::4])
        lv = np.clip((level.ravel() * (NOISE_BINS / 256.0)).astype(np.int32), 0, NOISE_BINS - 1)
        ad = np.minimum((np.abs(diff.ravel()) * (1.0 / NOISE_STEP_DN)).astype(np.int32), NOISE_STEPS - 1)
        hist = np.bincount(lv * NOISE_STEPS + ad, minlength=NOISE_BINS * NOISE_STEPS).reshape(NOISE_BINS, NOISE_STEPS)
        mid2 = ((np.arange(NOISE_STEPS) + 0.5) * NOISE_STEP_DN) ** 2
        bins = np.flatnonzero(hist.sum(axis=1) >= NOISE_BIN_MIN)
        if not len(bins):
            return lambda lv: np.full(np.shape(lv), MIN_NOISE_DN, np.float32)
        h = hist[bins]
        keep = np.cumsum(h, axis=1) <= TRIM_QUANTILE * h.sum(axis=1, keepdims=True)   # the central 98 % of |diff|
        keep[:, 0] = True
        hk = h * keep
        rms = np.sqrt((hk * mid2).sum(axis=1) / np.maximum(hk.sum(axis=1), 1))
        centres = (bins + 0.5) * 256.0 / NOISE_BINS
        sig = np.maximum(rms / TRIMMED_RMS_PER_SIGMA, MIN_NOISE_DN)
        lut = np.interp(np.arange(257, dtype=np.float64), centres, sig).astype(np.float32)   # per grey level
        return lambda lv: lut[np.clip(np.asarray(lv) + 0.5, 0, 256).astype(np.int32)]


def _window_fits(mean: np.ndarray, image: np.ndarray, balls_px: np.ndarray, noise_model):
    """One Lucas-Kanade step in a window round each ball (all windows of one size: the largest
    ball's radius + :data:`WINDOW_MARGIN_PX` each side, moved inside the frame where a ball is
    near its edge), all at once: the grey of the new frame ``image`` (BGR uint8) minus the
    ``mean``'s grey (BGR float32) minus their median difference (DN) = the mean's gradient x
    shift + offset, each pixel weighted by 1 / its noise (``noise_model(level, diff, step)``
    fitted to the windows' differences: :meth:`StillFrames._noise_model`). None without a
    window with gradient,
    else for those windows, in the balls' order: (their balls' centres (m, 2) px, shifts (m, 2)
    px, the shifts' covariances (m, 2, 2) px^2 summed over :data:`BLOCK_PX` blocks of the
    residuals' scores (the noise is correlated over a few px), the residuals' mean squares per
    noise variance (m,), the number of blocks per window, the median noise of the windows'
    difference (DN))."""
    H, W = image.shape[:2]
    balls = balls_px[np.all(np.isfinite(balls_px), axis=1)][:MAX_WINDOWS]
    if not len(balls):
        return None
    g = int(np.ceil(float(balls[:, 2].max()) + WINDOW_MARGIN_PX))
    side = max(2 * g + 1, 2 * BLOCK_PX)
    if side + 2 > min(H, W):
        return None
    n = len(balls)
    x0 = np.clip(np.round(balls[:, 0]).astype(int) - g, 1, W - 1 - side)
    y0 = np.clip(np.round(balls[:, 1]).astype(int) - g, 1, H - 1 - side)
    m = cv2.transform(np.concatenate([mean[y - 1:y + side + 1, x - 1:x + side + 1] for x, y in zip(x0, y0)]),
                      GREY_ROW).reshape(n, side + 2, side + 2)
    new = cv2.cvtColor(np.concatenate([image[y:y + side, x:x + side] for x, y in zip(x0, y0)]),
                       cv2.COLOR_BGR2GRAY).reshape(n, side, side)
    mc = m[:, 1:-1, 1:-1]
    diff = new - mc
    diff -= np.float32(_median(diff[:, ::2, ::2].ravel()))
    sig = noise_model(mc[:, ::2, ::2].ravel(), diff[:, ::2, ::2].ravel(), False)(mc)     # a quarter measures it
    noise = _median(sig[:, ::2, ::2].ravel())
    wt = 1.0 / sig
    # float32 rows (x gradient, y gradient, 1) x weight, their products summed by BLAS (matmul)
    A = np.empty((n, 3, side, side), np.float32)
    np.multiply(m[:, 1:-1, 2:] - m[:, 1:-1, :-2], 0.5 * wt, out=A[:, 0])
    np.multiply(m[:, 2:, 1:-1] - m[:, :-2, 1:-1], 0.5 * wt, out=A[:, 1])
    A[:, 2] = wt
    Af = A.reshape(n, 3, -1)
    df = (diff * wt).reshape(n, -1, 1)
    N = np.matmul(Af, Af.transpose(0, 2, 1)).astype(np.float64)
    det = np.linalg.det(N)
    good = np.isfinite(det) & (det > 1e-12 * np.einsum("nii->n", N) ** 3)
    if not good.any():
        return None
    Af, df, N = Af[good], df[good], N[good]
    Ninv = np.linalg.inv(N)
    p = np.einsum("nij,nj->ni", Ninv, np.matmul(Af, df)[..., 0].astype(np.float64))
    res = df[..., 0] - np.matmul(p.astype(np.float32)[:, None, :], Af)[:, 0]
    ratio = np.einsum("nk,nk->n", res, res).astype(np.float64) / max(side * side - 3, 1)
    # the scores summed over BLOCK_PX x BLOCK_PX blocks: (k, side) @ scores @ (side, k)
    B = _block_summer(side)
    k = B.shape[0]
    sc = (Af * res[:, None, :]).reshape(-1, 3, side, side)
    S = (B @ sc @ B.T).reshape(-1, 3, k * k)
    cov = (Ninv @ np.matmul(S, S.transpose(0, 2, 1)).astype(np.float64) @ Ninv)[:, :2, :2] * (k * k / (k * k - 1.0))
    ok = np.all(np.isfinite(cov), axis=(1, 2)) & (cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] * cov[:, 1, 0] > 0)
    if not ok.any():
        return None
    return balls[good][ok, :2], p[ok, :2], cov[ok], ratio[ok], k * k, noise


def _block_means(img: np.ndarray, grey: bool = True) -> np.ndarray:
    """``img`` in :data:`SUBSAMPLE` x :data:`SUBSAMPLE` block means (float32): a uint8 grey frame
    (``grey``), or any float32 array."""
    H, W = img.shape[:2]
    return cv2.resize(img.astype(np.float32) if grey else img, (max(W // SUBSAMPLE, 1), max(H // SUBSAMPLE, 1)),
                      interpolation=cv2.INTER_AREA)


def _median(a: np.ndarray) -> float:
    """The median of a 1D array (np.median without its overhead; the upper middle value of an
    even count)."""
    k = a.size // 2
    return float(np.partition(a, k)[k]) if a.size else 0.0


@lru_cache(maxsize=64)
def _block_summer(side: int) -> np.ndarray:
    """(side // BLOCK_PX, side) float32: 1 where a pixel of a row (or column) of ``side`` px is in
    a block (the last ``side % BLOCK_PX`` px in none)."""
    k = side // BLOCK_PX
    B = np.zeros((k, side), np.float32)
    for i in range(k):
        B[i, i * BLOCK_PX:(i + 1) * BLOCK_PX] = 1.0
    B.setflags(write=False)
    return B


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


def ball_windows(det, rules) -> np.ndarray:
    """The balls of detection ``det`` (:class:`~.detection.Detection`) whose windows
    :meth:`StillFrames.add` tests in the next frame:
    (m, 3) centre x, y and radius (px; the minor semi-axis), the accepted ones first, then the
    refused candidates of a ball's size (within -25 / +35 % of the accepted balls' median minor
    semi-axis; without accepted balls, ``rules.radius_range_px``)."""
    acc = [(float(f.centre_px[0]), float(f.centre_px[1]), float(min(f.axes_px))) for f in det.fiducials]
    if acc:
        med = float(np.median([r for _, _, r in acc]))
        lo, hi = 0.75 * med, 1.35 * med
    elif hasattr(rules, "radius_range_px"):
        lo, hi = 0.8 * float(rules.radius_range_px[0]), 1.2 * float(rules.radius_range_px[1])
    else:
        lo, hi = 0.0, np.inf
    rej = [(float(f.centre_px[0]), float(f.centre_px[1]), float(min(f.axes_px))) for f in det.rejected
           if lo <= float(min(f.axes_px)) <= hi]
    return np.array(acc + rej, float).reshape(-1, 3)
