"""Frames of a still head pooled (issue 28 item 3): means, the scatter that measures the noise,
and the motion test that restarts the pool (vision.still_pool)."""

from __future__ import annotations

import numpy as np

from monotracker.registration.quantiles import chi2_ppf
from monotracker.vision.still_pool import StillPool

FXY = np.array([1000.0, 1000.0])


def _balls(k: int = 6, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-0.1, 0.1, (k, 2))      # normalised coordinates


def test_still_frames_pool_to_their_mean_and_measure_the_noise():
    rng = np.random.default_rng(1)
    true = _balls()
    sigma = 0.2
    pool = StillPool(max_frames=8)
    frames = [true + rng.normal(0, sigma, true.shape) / FXY for _ in range(8)]
    joined = [pool.add(k, range(6), f, FXY, sigma) for k, f in enumerate(frames)]
    st = pool.stats()
    assert joined[0] is False and all(joined[1:])
    np.testing.assert_allclose(st.means, np.mean(frames, axis=0), atol=1e-15)
    assert st.frames == 8 and list(st.counts) == [8] * 6 and st.noise_dof == 2 * 6 * 7
    assert 0.8 * sigma < st.noise_px < 1.2 * sigma


def test_a_head_that_moves_restarts_the_pool_and_a_still_one_rarely_does():
    rng = np.random.default_rng(2)
    true = _balls()
    sigma = 0.2
    restarts, trials = 0, 400
    for _ in range(trials):
        pool = StillPool(max_frames=8, alpha=1e-2)
        for k in range(8):
            still = pool.add(k, range(6), true + rng.normal(0, sigma, true.shape) / FXY, FXY, sigma)
            restarts += (k > 0) and not still
    # per-frame false alarm rate near alpha (the test's chi-square law), far below 5 %
    assert restarts / (7 * trials) < 0.03
    # a whole-head shift of 1 px (5 sigma) on frame 5: the pool restarts there and holds 1 frame
    pool = StillPool(max_frames=8)
    for k in range(5):
        pool.add(k, range(6), true + rng.normal(0, sigma, true.shape) / FXY, FXY, sigma)
    moved = true + np.array([1.0, 0.0]) / FXY
    assert pool.add(5, range(6), moved + rng.normal(0, sigma, true.shape) / FXY, FXY, sigma) is False
    assert pool.stats().frames == 1
    assert chi2_ppf(1 - 1e-3, 12) < 6 * 25 / (1 + 1 / 5)    # why 1 px must be caught: its distance


def test_the_window_keeps_only_the_last_frames():
    true = _balls()
    pool = StillPool(max_frames=3)
    for k in range(10):
        pool.add(k, range(6), true, FXY, 0.2)
    assert pool.stats().frames == 3 and len(pool) == 3
