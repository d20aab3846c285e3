"""Ball colour learned from one click, saved with the calibration, used by the detector."""

import numpy as np
import pytest

from monotracker.errors import InputError
from monotracker.sim.camera_sim import SimulatedCamera
from monotracker.sim.optics import Optics
from monotracker.vision.ball_colour import BallColour, learn_ball_colour
from monotracker.vision.camera_model import CameraModel, default_camera
from monotracker.vision.detect_classical import ClassicalDetector

MAGENTA = (170.0, 50.0, 190.0)     # BGR, hue ~154 (orange would share the skin's hue)


@pytest.fixture(scope="module")
def magenta_frame():
    cam = SimulatedCamera(seed=5, optics=Optics(drapes="mixed"), ball_bgr=MAGENTA)
    return cam.render(0.0)


def test_learned_magenta_balls_are_detected_default_green_finds_none(magenta_frame):
    img, tr = magenta_frame
    colour = learn_ball_colour(img, tr.ellipse_centres_px[4] + [1.0, -1.0])
    assert colour.hue_lo < 154 < colour.hue_hi
    assert ClassicalDetector().detect(img).fiducials == []
    d = ClassicalDetector(colour=colour).detect(img)
    # hair may cross a ball's edge, JPEG blocks may dent one: such a ball is refused (never a
    # biased centre); at most two of nine here
    assert len(d.fiducials) >= 7 and int(tr.visible.sum()) == 9
    err = np.linalg.norm(d.centres[:, None] - tr.ellipse_centres_px[None], axis=2).min(1)
    assert err.max() < 0.35


def test_learned_green_band_excludes_a_green_blue_drape():
    """The default band (hue 35-90) takes in a green-blue drape (hue ~86); a learned band does not."""
    cam = SimulatedCamera(seed=1, optics=Optics(drapes="green-blue", jpeg_quality=95))
    img, tr = cam.render(0.0)
    colour = learn_ball_colour(img, tr.ellipse_centres_px[0])
    assert colour.hue_hi < 84 and colour.hue_lo > 35
    m_default = ClassicalDetector().mask(img)
    m_learned = ClassicalDetector(colour=colour).mask(img)
    assert m_default[5:60, 5:60].mean() > 200 and m_learned[5:60, 5:60].mean() < 5
    assert len(ClassicalDetector(colour=colour).detect(img).fiducials) == 9


@pytest.mark.parametrize("where, reason", [
    ("skin", "ball"),
    ("drape", "larger than a ball"),
    ("outside", "outside"),
])
def test_click_off_a_ball_is_refused_with_a_reason(magenta_frame, where, reason):
    img, tr = magenta_frame
    c = tr.ellipse_centres_px
    xy = {"skin": c.mean(0) + [0.0, 30.0] if np.linalg.norm(c - (c.mean(0) + [0, 30]), axis=1).min() > 20
          else c.mean(0) + [30.0, 0.0],
          "drape": (20.0, 20.0), "outside": (5000.0, 3.0)}[where]
    with pytest.raises(InputError, match=reason):
        learn_ball_colour(img, xy)


def test_colour_band_validation():
    with pytest.raises(InputError, match="wider than 70"):
        BallColour(10, 120, 90, 35)
    with pytest.raises(InputError, match="saturation minimum"):
        BallColour(35, 90, 10, 35)
    red = BallColour(170, 8, 80, 30)          # wraps through 0
    img = np.zeros((4, 4, 3), np.uint8)
    img[0, 0] = (20, 20, 220)                  # red: hue ~0
    img[0, 1] = (40, 160, 40)                  # green
    m = red.mask(img)
    assert m[0, 0] == 255 and m[0, 1] == 0


@pytest.mark.parametrize("suffix", [".json", ".yml"])
def test_colour_saved_with_the_calibration(tmp_path, suffix):
    cam = default_camera()
    plain = cam.save(tmp_path / f"plain{suffix}")
    assert CameraModel.load(plain).ball_colour is None
    cam.ball_colour = BallColour(5, 22, 110, 40)
    p = cam.save(tmp_path / f"cam{suffix}")
    back = CameraModel.load(p)
    assert back.ball_colour == BallColour(5, 22, 110, 40)
    assert np.allclose(back.K, cam.K)


def test_bad_colour_in_a_calibration_file_is_one_line(tmp_path):
    import json

    d = default_camera().to_dict()
    d["ball_colour"] = {"hue_lo": 10, "hue_hi": 150, "sat_min": 90, "val_min": 35}
    p = tmp_path / "c.json"
    p.write_text(json.dumps(d))
    with pytest.raises(InputError, match="ball_colour: hue band"):
        CameraModel.load(p)
