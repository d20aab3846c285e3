"""Session.learn_ball_colour: one click on the live simulated frame; refusals are one line."""

import numpy as np
import pytest

from monotracker.engine.ball_colour_cmd import learn_ball_colour_from_frame
from monotracker.errors import MonoTrackerError
from monotracker.sim.camera_sim import SimulatedCamera
from monotracker.vision.camera_model import CameraModel, default_camera

from .conftest import plan_sample


def test_learn_on_the_live_sim_frame(make_session):
    s = make_session(clock="sim")
    r = s.learn_ball_colour(100, 100)
    assert not r.ok and "camera" in r.message
    plan_sample(s)
    assert s.start_camera().ok
    s.advance(0.2)
    rig = s._loop.camera.rig
    img, _, _ = rig.latest_frame()
    truth = rig._last_frame.truth
    k = int(np.argmax(truth.visible))
    x, y = truth.ellipse_centres_px[k]
    r = s.learn_ball_colour(x, y)
    assert r.ok, r.message
    assert "not saved" in r.message
    col = rig.tracker.detector.colour
    assert col is not None and col.hue_lo < 60 < col.hue_hi        # green balls: hue ~58
    r = s.learn_ball_colour(5, 5)                                   # the drape in the corner
    assert not r.ok and "ball" in r.message
    assert rig.tracker.detector.colour == col                       # a refusal changes nothing


class _FakeRig:
    def __init__(self, image):
        self.image, self.colour, self.index = image, None, 1

    def latest_frame(self):
        return self.image, self.index, None

    def set_ball_colour(self, colour):
        self.colour = colour
        return ""


def test_learned_colour_is_saved_in_the_calibration_file(tmp_path):
    cam = SimulatedCamera(seed=3, ball_bgr=(200.0, 90.0, 40.0))         # blue balls
    img, tr = cam.render(0.0)
    calib = default_camera().save(tmp_path / "camera.json")
    rig = _FakeRig(img)
    got = learn_ball_colour_from_frame(rig, str(calib), *tr.ellipse_centres_px[2])
    assert got.saved_to == str(calib) and rig.colour == got.colour
    assert CameraModel.load(calib).ball_colour == got.colour
    assert 95 < got.colour.hue_lo < 110 < got.colour.hue_hi           # blue: hue ~107


def test_learns_from_the_clicked_frame_not_a_newer_one(tmp_path):
    """The user clicked a ball on frame A; by the click the camera's newest frame is another one
    where that pixel is drape: the colour comes from A (frame=), or a one-line refusal
    (frame_index=), never from the newer frame."""
    cam = SimulatedCamera(seed=3, ball_bgr=(200.0, 90.0, 40.0))         # blue balls
    shown, tr = cam.render(0.0)
    x, y = tr.ellipse_centres_px[2]
    drape = np.empty_like(shown)
    drape[:] = shown[5, 5]                                              # the head moved: drape everywhere
    rig = _FakeRig(drape)
    rig.index = 8
    calib = default_camera().save(tmp_path / "camera.json")
    got = learn_ball_colour_from_frame(rig, str(calib), x, y, frame=shown, frame_index=7)
    assert rig.colour == got.colour and 95 < got.colour.hue_lo < 110 < got.colour.hue_hi
    assert CameraModel.load(calib).ball_colour == got.colour
    # only the index of the shown frame: the newest is another one -> refused, nothing changed
    rig2 = _FakeRig(drape)
    rig2.index = 8
    with pytest.raises(MonoTrackerError, match="changed since it was shown") as exc:
        learn_ball_colour_from_frame(rig2, str(calib), x, y, frame_index=7)
    assert "\n" not in str(exc.value) and rig2.colour is None
    assert CameraModel.load(calib).ball_colour == got.colour
    # the same frame still newest: learned on it
    rig3 = _FakeRig(shown)
    rig3.index = 7
    assert learn_ball_colour_from_frame(rig3, None, x, y, frame_index=7).colour == got.colour
