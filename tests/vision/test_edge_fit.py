"""Edge-fit centres on images made independently of our simulator: a supersampled disc with
shading and a specular highlight, on backgrounds of two colours, blurred in linear light,
gamma-encoded (what a lens and a camera do), with the true centre known exactly."""

import cv2
import numpy as np
import pytest

from monotracker.vision.detection import refine_blob
from monotracker.vision.edge_fit import BLUR_PER_WIDTH, fit_ball_edge, fit_ball_edges, measure_edge_blur

SS = 8                       # supersampling factor
BALL = np.array([40.0, 160.0, 45.0])      # BGR, display space
SKIN = np.array([140.0, 165.0, 205.0])
DRAPE = np.array([150.0, 105.0, 45.0])    # blue drape: positive green chromaticity
GLOVE = np.array([175.0, 195.0, 215.0])


def render_ball(centre, radius, size=72, blur_sigma=1.2, background="split", highlight=True, cut=None,
                noise=0.0, seed=0):
    """(BGR uint8 image, true centre). Pixel (i, j) covers [j - 0.5, j + 0.5] (OpenCV centres)."""
    n = size * SS
    g = (np.arange(n) + 0.5) / SS - 0.5
    xx, yy = np.meshgrid(g, g)
    lin = lambda c: (np.asarray(c, float) / 255.0) ** 2.2
    img = np.empty((n, n, 3))
    if isinstance(background, str):  # "split": drape left of x = centre - 3, skin right of it
        img[:] = lin(SKIN)
        img[xx < centre[0] - 3] = lin(DRAPE)
    else:
        img[:] = lin(background)
    dx, dy = xx - centre[0], yy - centre[1]
    rho2 = (dx**2 + dy**2) / radius**2
    inside = rho2 <= 1.0
    nz = np.sqrt(np.clip(1 - rho2, 0, 1))
    light = np.array([-0.3, -0.5, 0.81]) / np.linalg.norm([-0.3, -0.5, 0.81])
    shade = 0.25 + 0.75 * np.clip(dx / radius * light[0] + dy / radius * light[1] + nz * light[2], 0, 1)
    ball = lin(BALL)[None, None, :] * shade[..., None]
    if highlight:
        hx, hy = centre[0] - 0.25 * radius, centre[1] - 0.35 * radius
        ball = ball + 1.2 * np.exp(-((xx - hx) ** 2 + (yy - hy) ** 2) / (2 * (0.12 * radius) ** 2))[..., None]
    img[inside] = ball[inside]
    if cut is not None:              # an occluder (glove) covering x > cut
        img[xx > cut] = lin(GLOVE)
    img = cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)        # pixel integration
    img = cv2.GaussianBlur(img, (0, 0), blur_sigma)                           # lens (linear light)
    if noise:
        img = img + np.random.default_rng(seed).normal(0, noise, img.shape)
    out = np.clip(np.clip(img, 0, 1) ** (1 / 2.2) * 255 + 0.5, 0, 255).astype(np.uint8)
    return out, np.asarray(centre, float)


def coarse(img, centre, radius):
    """A coarse ellipse like the detector's contour gives: off by ~0.5 px and 1 px in radius."""
    return (centre[0] + 0.4, centre[1] - 0.3), (radius + 0.8, radius + 0.8), 0.0


@pytest.mark.parametrize("radius", [5.0, 9.0, 18.0, 28.0])
def test_centre_of_a_blurred_glossy_ball_on_drape_and_skin(radius):
    size = int(2 * radius + 40)
    errs = []
    for k, off in enumerate([(0.13, 0.71), (0.5, 0.25), (0.87, 0.42)]):
        c = (size / 2 + off[0], size / 2 + off[1])
        img, truth = render_ball(c, radius, size=size, noise=0.002, seed=k)
        (cx, cy), ax, ang = coarse(img, truth, radius)
        fit = fit_ball_edge(img, (cx, cy), ax, ang)
        assert fit.ok, fit.reason
        errs.append(np.linalg.norm(fit.centre_px - truth))
        assert abs(np.mean(fit.axes_px) - radius) < 0.6
    # a 5 px ball's highlight (at 0.43 r, blurred) reaches its rim: the rays there are dropped,
    # but fewer rays remain; the bigger balls meet the 0.06 px target
    tol = 0.16 if radius < 6 else 0.06
    assert np.mean(errs) < tol and max(errs) < 2 * tol, errs


def test_chroma_centroid_is_pulled_towards_the_drape_the_edge_fit_is_not():
    """The old soft-chromaticity centroid on the same image: biased towards the blue drape
    (that is what the edge fit replaces). Guards the test's power, not a target."""
    radius = 9.0
    img, truth = render_ball((36.3, 36.6), radius, blur_sigma=1.5)
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    mask = cv2.inRange(hsv, (35, 90, 35), (90, 255, 255))
    cnts, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cnt = max(cnts, key=cv2.contourArea)
    old = refine_blob(img, cnt)[0]
    (cx, cy), ax, ang = coarse(img, truth, radius)
    new = fit_ball_edge(img, (cx, cy), ax, ang).centre_px
    assert np.linalg.norm(old - truth) > 0.2
    assert np.linalg.norm(new - truth) < 0.06


def test_ball_cut_by_an_occluder_is_refused_or_unbiased():
    radius = 10.0
    for cut_at in (0.2, 0.5, 0.7, 0.8):   # occluder edge at +0.2 r ... +0.8 r from the centre
        c = np.array([36.4, 36.2])
        img, truth = render_ball(c, radius, background=SKIN, cut=c[0] + cut_at * radius)
        (cx, cy), ax, ang = coarse(img, truth, radius)
        fit = fit_ball_edge(img, (cx - 2, cy), ax, ang)
        assert (not fit.ok) or np.linalg.norm(fit.centre_px - truth) < 0.15, fit


def test_no_ball_no_fit():
    img = np.full((80, 80, 3), 120, np.uint8)
    fit = fit_ball_edge(img, (40, 40), (9, 9), 0.0)
    assert not fit.ok and fit.reason


def test_ball_at_the_image_border_is_refused():
    img, truth = render_ball((8.0, 36.0), 9.0)
    fit = fit_ball_edge(img, (8.0, 36.0), (9, 9), 0.0)
    assert not fit.ok and "border" in fit.reason


def test_measured_blur_follows_the_lens_blur():
    """The 25-75 % rise of an edge blurred by a Gaussian of sigma is 1.349 sigma (the pixel's
    box adds ~0.3 px in quadrature, negligible at sigma 2): the measured blur is
    BLUR_PER_WIDTH x that width, and grows with the lens blur."""
    def measured(sigma, radius):
        size = int(2 * radius + 40)
        img, truth = render_ball((size / 2 + 0.3, size / 2 + 0.6), radius, size=size, blur_sigma=sigma,
                                 noise=0.002)
        (cx, cy), ax, ang = coarse(img, truth, radius)
        return measure_edge_blur(img, [((cx, cy), (2 * ax[0], 2 * ax[1]), ang)])

    for radius in (9.0, 18.0):
        b2, b1 = measured(2.0, radius), measured(1.0, radius)
        expect = BLUR_PER_WIDTH * 1.349 * 2.0
        assert abs(b2 - expect) < 0.12 * expect, (b2, expect)
        assert b1 < 0.65 * b2, (b1, b2)


@pytest.mark.parametrize("sigma", [0.5, 0.8, 2.0])
def test_centres_hold_from_sharp_to_strongly_blurred_balls(sigma):
    """The fit's windows follow the measured blur: centres hold on sharp and on strongly
    blurred balls alike (glossy ball, drape and skin behind it)."""
    errs = []
    for radius in (6.0, 9.0, 18.0):
        size = int(2 * radius + 40)
        for k, off in enumerate([(0.13, 0.71), (0.5, 0.25), (0.87, 0.42)]):
            img, truth = render_ball((size / 2 + off[0], size / 2 + off[1]), radius, size=size,
                                     blur_sigma=sigma, noise=0.002, seed=k)
            (cx, cy), ax, ang = coarse(img, truth, radius)
            fit = fit_ball_edge(img, (cx, cy), ax, ang)
            assert fit.ok, fit.reason
            errs.append(np.linalg.norm(fit.centre_px - truth))
    assert np.mean(errs) < 0.04 and max(errs) < 0.08, errs


def test_degenerate_edge_points_are_refused_not_raised():
    """Edge points all alike (no outline to fit) with a known shape: no fit, no exception."""
    from monotracker.vision.edge_fit import _robust_ellipse

    pts = np.full((16, 2), 30.0)
    assert _robust_ellipse(pts, np.ones(16, bool), (0.9, 10.0)) is None
    with pytest.raises(ValueError, match="shapes"):
        fit_ball_edges(np.zeros((60, 60, 3), np.uint8), [((30, 30), (18, 18), 0.0)], 1.5, [])
