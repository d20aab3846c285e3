"""The classical detector's second look in the balls' own hue (issue 28; on by default:
``ClassicalDetector.narrow_second_pass``, ``ball_colour.band_of_balls``): a green ball lying on a
teal drape (both inside the wide default band) merges with the drape into one blob that is no
ball, and is lost; thresholded with the hue band of the balls found elsewhere in the frame it is
found again, at its drawn centre. Synthetic frames drawn here (anti-aliased discs, a little blur):
the truth is where each disc was drawn."""

import cv2
import numpy as np
import pytest

from monotracker.vision.ball_colour import BallColour, band_of_balls
from monotracker.vision.detect_classical import ClassicalDetector
from monotracker.vision.detection import BlobRules

BALL_HUE, DRAPE_HUE = 57, 80          # OpenCV hue (0-180): green dye, teal drape (as rendered, issue 28)


def _bgr(h, s, v):
    return tuple(int(x) for x in cv2.cvtColor(np.uint8([[[h, s, v]]]), cv2.COLOR_HSV2BGR)[0, 0])


def _frame(on_drape_dy: float):
    """Skin above, a teal drape below y = 300; four balls on the skin and one whose centre lies
    ``on_drape_dy`` px above the drape's edge (< 14: it lies partly on the drape)."""
    img = np.zeros((480, 640, 3), np.uint8)
    img[:] = _bgr(12, 90, 200)
    cv2.rectangle(img, (0, 300), (639, 479), _bgr(DRAPE_HUE, 170, 110), -1)
    centres = np.array([(120.3, 120.6), (260.7, 140.2), (400.1, 110.9), (520.6, 180.4), (330.4, 300.0 - on_drape_dy)])
    for cx, cy in centres:
        cv2.circle(img, (int(round(cx * 16)), int(round(cy * 16))), 14 * 16, _bgr(BALL_HUE, 180, 150), -1, cv2.LINE_AA,
                   shift=4)
    return cv2.GaussianBlur(img, (0, 0), 0.8), centres


def _found(det, img, centres):
    d = det.detect(img)
    got = np.array([f.centre_px for f in d.fiducials]).reshape(-1, 2)
    err = [float(np.min(np.linalg.norm(got - c, axis=1))) if len(got) else np.inf for c in centres]
    return d, np.array(err)


@pytest.mark.parametrize("dy", [14.0, 8.0])
def test_a_ball_on_a_drape_of_a_neighbouring_hue_is_found_with_the_balls_own_band(dy):
    img, centres = _frame(dy)
    rules = BlobRules(radius_mm=5.0, focal_px=1200.0)
    d0, err0 = _found(ClassicalDetector(rules, narrow_second_pass=False), img, centres)
    assert np.all(err0[:4] < 0.1) and err0[4] > 5.0          # the wide band alone loses the ball on the drape
    d1, err1 = _found(ClassicalDetector(rules), img, centres)                  # the default
    assert len(d1.fiducials) == 5 and np.all(err1 < 0.15), err1
    (new,) = [f for f in d1.fiducials if "narrowed_band" in f.features]
    lo, hi = new.features["narrowed_band"]
    assert lo <= BALL_HUE <= hi < DRAPE_HUE
    assert any("touches the image border" in r.reason for r in d1.rejected)   # the drape stays refused


def test_the_band_of_the_balls_found_lies_inside_the_band_searched_and_leaves_the_drape_out():
    img, centres = _frame(14.0)
    det = ClassicalDetector(BlobRules(radius_mm=5.0, focal_px=1200.0))
    d = det.detect(img)
    band = band_of_balls(img, d.fiducials, det.band())
    assert band is not None and 35 <= band.hue_lo <= BALL_HUE <= band.hue_hi < DRAPE_HUE <= 90
    assert (band.sat_min, band.val_min) == (det.sat_min, det.val_min)
    assert band_of_balls(img, [], det.band()) is None
    assert band_of_balls(img, d.fiducials, BallColour(170, 10, 90, 35)) is None     # a band through hue 0
