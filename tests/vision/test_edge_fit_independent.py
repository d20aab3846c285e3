"""Edge-fit centres against the truth of a renderer that shares no code with monotracker.sim
(``independent_render.py``): blur 1.5 px defocus disc + 0.5 px Gaussian, Bayer, shot and read
noise, sRGB, JPEG 85; and a sharp lens (0.4 px Gaussian, Bayer, no JPEG). Errors in px; 60
balls of radius 7-13 px per test, fixed seed."""

from __future__ import annotations

import numpy as np
from independent_render import Imaging, render_ball

from monotracker.vision.detect_classical import ClassicalDetector

BLURRED_JPEG = Imaging(defocus_px=1.5, gauss_px=0.5, jpeg_quality=85)
SHARP_RAW = Imaging(defocus_px=0.0, gauss_px=0.4, jpeg_quality=0)


def _errors(split: bool, n: int = 60, seed: int = 2, imaging: Imaging = BLURRED_JPEG) -> np.ndarray:
    """Per ball the centre error (px) of the classical detector's edge fit; NaN = not found
    within 3 px."""
    rng = np.random.default_rng(seed)
    det = ClassicalDetector()
    out = np.full(n, np.nan)
    for i in range(n):
        img, truth = render_ball(rng, float(rng.uniform(7.0, 13.0)), imaging, split=split)
        d = det.detect(img)
        if len(d.centres):
            e = np.linalg.norm(np.asarray(d.centres) - truth, axis=1).min()
            if e < 3.0:
                out[i] = e
    return out


def test_blurred_jpeg_one_background_colour():
    """One background colour: mean error 0.174 px here (recall 0.65); the edge fit before the
    near background (each ray's background the line through its two outer eighths) gives 0.232
    px and fails (seeds 0-5: 0.11-0.19 px vs 0.20-0.29 px)."""
    e = _errors(split=False)
    found = ~np.isnan(e)
    assert found.mean() >= 0.5
    assert e[found].mean() < 0.20


def test_blurred_jpeg_two_background_colours():
    """A colour boundary through the ball or just beyond its edge (a ball on the head's
    outline): mean error 0.190 px here (recall 0.58; the line background 0.289 px). A check with
    margin, not a separation: seeds 0-5 give 0.16-0.25 px, the line background 0.18-0.32 px."""
    e = _errors(split=True)
    found = ~np.isnan(e)
    assert found.mean() >= 0.4
    assert e[found].mean() < 0.30


def test_sharp_lens_bayer_fringes_do_not_refuse_balls():
    """A sharp lens: demosaicing puts false colour on the ball's edge, which the unmixing's
    residual check took for a third colour (an outline at the ball) and refused most rays:
    recall 0.70 here with the residual tolerance 0.12 of round 5 (seeds 0-5: 0.63-0.73), 0.96
    for such balls without the mosaic. The tolerance now follows the measured edge blur
    (``edge_fit.SHARP_UNMIX_RESIDUAL``): recall 0.82 here (seeds 0-5: 0.75-0.88), mean error
    0.065 px (0.072 before). The bound equals the worst seed's recall: little margin."""
    e = _errors(split=False, imaging=SHARP_RAW)
    found = ~np.isnan(e)
    assert found.mean() >= 0.75
    assert e[found].mean() < 0.09
