"""The edge fit's contact-shadow rays (edge_fit._without_shadow_rays, issue 28) on a ball drawn
here from its geometry, independently of our simulator: a shaded sphere lit from one side with a
soft dark shadow on the background beside its other side, the true centre known exactly."""

import cv2
import numpy as np
import pytest

from monotracker.vision import edge_fit

SS = 8                                      # supersampling factor
BALL = np.array([40.0, 160.0, 45.0])        # BGR, display space
SKIN = np.array([140.0, 165.0, 205.0])


def _lin(c):
    return (np.asarray(c, float) / 255.0) ** 2.2


def _draw_ball(centre, radius, size, shadow_deg, depth, width_px, lobe, ambient, diffuse, tint, blur_sigma,
               cut_x=None):
    """BGR uint8 image of a Lambertian sphere (radius px, centre px; pixel (i, j) covers
    [j - 0.5, j + 0.5]) on skin, lit from the side opposite ``shadow_deg`` (image angle, deg,
    from +x towards +y; shading ``ambient + diffuse x cos``), with a contact shadow on the
    background beside the outline: the skin's light times 1 - depth x exp(-d / width_px) x
    cos^lobe (the angle from ``shadow_deg``), d the distance outside the outline (px); the limb
    takes on the skin's colour (``tint`` at the outline, 0 from half the radius in); ``cut_x``
    (px): every pixel right of x = cut_x is a grey instrument instead; then pixel integration, a
    Gaussian lens blur in linear light and gamma 2.2. Also returns the shadow's unit direction."""
    n = size * SS
    g = (np.arange(n) + 0.5) / SS - 0.5
    xx, yy = np.meshgrid(g, g)
    dx, dy = xx - centre[0], yy - centre[1]
    rr = np.hypot(dx, dy)
    sv = np.array([np.cos(np.radians(shadow_deg)), np.sin(np.radians(shadow_deg))])
    facing = np.clip((dx * sv[0] + dy * sv[1]) / np.maximum(rr, 1e-9), 0.0, 1.0) ** lobe
    shadow = depth * facing * np.exp(-np.clip(rr - radius, 0.0, None) / width_px)
    img = _lin(SKIN)[None, None, :] * (1.0 - shadow)[..., None]
    inside = rr <= radius
    nz = np.sqrt(np.clip(1.0 - (rr / radius) ** 2, 0.0, 1.0))
    light = np.array([-0.6 * sv[0], -0.6 * sv[1], 0.8])
    shade = ambient + diffuse * np.clip((dx * light[0] + dy * light[1]) / radius + nz * light[2], 0.0, 1.0)
    w = tint * np.clip((rr / radius - 0.5) / 0.5, 0.0, 1.0)
    colour = _lin(BALL)[None, None, :] * (1.0 - w[..., None]) + 0.3 * _lin(SKIN)[None, None, :] * w[..., None]
    img[inside] = (colour * shade[..., None])[inside]
    if cut_x is not None:
        img[xx > cut_x] = _lin([120.0, 120.0, 125.0])
    img = cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    return np.clip(np.clip(img, 0, 1) ** (1 / 2.2) * 255 + 0.5, 0, 255).astype(np.uint8), sv


def shadowed_ball(centre, radius, size, shadow_deg=200.0, depth=0.8, width_px=2.0, lobe=4, blur_sigma=1.0):
    """:func:`_draw_ball` with a moderate shadow and the ball's own colour to its outline."""
    return _draw_ball(centre, radius, size, shadow_deg, depth, width_px, lobe, 0.15, 0.85, 0.0, blur_sigma)


def _fit(img, centre, radius):
    """The edge fit with the ball's outline known (a circle: the sphere on the optical axis),
    from a coarse ellipse ~0.5 px and 0.4 px in radius off, as the detector's contour gives."""
    ell = ((centre[0] + 0.4, centre[1] - 0.3), (2 * radius + 0.8, 2 * radius + 0.8), 0.0)
    return edge_fit.fit_ball_edges(img, [ell], shapes=[(1.0, 0.0)])[0]


@pytest.mark.parametrize("radius", [10.0, 16.0])
@pytest.mark.parametrize("offset", [(0.3, 0.6), (0.8, 0.1)])
def test_contact_shadow_does_not_pull_the_centre(radius, offset, monkeypatch):
    """Without the shadow rays left out, the centre moves ~0.28 px towards the shadow (the dark
    skin beside the unlit limb reads as ball); with them left out it stays within 0.12 px of the
    truth (the shadow's faint tail, < 0.3 px outside the fit, still pulls a little; the same ball
    without a shadow: <= 0.01 px)."""
    size = int(2 * radius + 40)
    centre = np.array([size / 2 + offset[0], size / 2 + offset[1]])
    img, towards_shadow = shadowed_ball(centre, radius, size)
    fixed = _fit(img, centre, radius)
    monkeypatch.setattr(edge_fit, "SHADOW_NF", 0.0)          # the shadow rays kept
    plain = _fit(img, centre, radius)
    assert fixed.ok and plain.ok, (fixed.reason, plain.reason)
    pull = plain.centre_px - centre
    assert np.linalg.norm(pull) > 0.2 and pull @ towards_shadow > 0.2, pull
    assert np.linalg.norm(fixed.centre_px - centre) < 0.12, fixed.centre_px - centre


def tinted_ball(centre, radius, size, shadow_deg=200.0, tint=0.5, blur_sigma=0.6, cut_x=None):
    """:func:`_draw_ball` as the Mitsuba frames show it (issue 28): the shadow is deep (0.95
    beside the unlit limb) and wide (2.5 px), and the ball's limb takes on the skin's colour (light
    the skin throws back: the ball's colour mixed with the skin's, ``tint`` at the outline falling
    to 0 at half the radius in); ``cut_x`` (px): a ball cut by a straight grey occluder."""
    return _draw_ball(centre, radius, size, shadow_deg, 0.95, 2.5, 2, 0.1, 0.9, tint, blur_sigma, cut_x)


@pytest.mark.xfail(strict=True, reason="issue 28 item 2 open: a deep contact shadow beside a limb that takes "
                   "on the skin's colour still pulls the centre ~0.4 px (docs/vision.md, per-ray locators)")
@pytest.mark.parametrize("radius", [6.0, 10.0])
def test_tinted_contact_shadow_does_not_pull_the_centre(radius):
    """What the Mitsuba frames show and the shadow-ray rule does not remove: with the shadow deep
    and the limb tinted, the centre lies 0.38 px off towards the shadow here (0.34-0.46 px at other
    sub-pixel offsets; 0.49-0.54 px without the rule). Within 0.15 px is the goal; it fails today
    (strict xfail: it says so when it passes)."""
    size = int(2 * radius + 40)
    centre = np.array([size / 2 + 0.3, size / 2 + 0.6])
    img, _ = tinted_ball(centre, radius, size)
    fit = _fit(img, centre, radius)
    assert fit.ok, fit.reason
    assert np.linalg.norm(fit.centre_px - centre) < 0.15, fit.centre_px - centre


@pytest.mark.parametrize("cut", [0.3, 0.5])
def test_a_shadowed_ball_cut_by_an_instrument_is_still_refused(cut):
    """A shaded ball with its contact shadow, cut 30 / 50 % of its radius by a straight grey
    instrument on its lit side (the shadow opposite): refused, whatever shading-related rule
    leaves rays out (the contact-shadow rays go, the chord stays and reaches the cut test)."""
    radius, size = 10.0, 60
    centre = np.array([30.3, 30.4])
    img, _ = tinted_ball(centre, radius, size, shadow_deg=180.0, cut_x=centre[0] + (1.0 - cut) * radius)
    fit = _fit(img, centre, radius)
    assert not fit.ok, fit


@pytest.mark.parametrize("shadow_deg", [200.0, 30.0])
def test_the_fit_says_where_it_left_shadow_rays_out(shadow_deg):
    """The shading check (issue 28) needs to know a contact shadow lies beside a ball and on which
    side: the fit reports how many rays it left out as a shadow's and their mean direction, which
    points towards the shadow drawn here (its direction known from the drawing); the same ball
    without a shadow reports none."""
    radius, size = 10.0, 60
    centre = np.array([30.3, 29.6])
    img, towards_shadow = tinted_ball(centre, radius, size, shadow_deg=shadow_deg)
    fit = _fit(img, centre, radius)
    assert fit.ok, fit.reason
    assert fit.shadow_rays >= 3, fit.shadow_rays
    d = np.asarray(fit.shadow_dir)
    assert d @ towards_shadow > 0.7 * np.linalg.norm(d) > 0.35, (d, towards_shadow)
    bare = _draw_ball(centre, radius, size, shadow_deg, 0.0, 2.5, 2, 0.1, 0.9, 0.0, 0.6)[0]
    none = _fit(bare, centre, radius)
    assert none.ok and none.shadow_rays == 0 and none.shadow_dir == (0.0, 0.0), (none.shadow_rays, none.shadow_dir)
