"""SessionConfig.camera_optics: a validated setting that really switches the twin camera to
photo-like frames (issue 13)."""

import numpy as np
import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.errors import InputError
from monotracker.sim.optics import PRESETS


def test_unknown_preset_and_non_sim_camera_are_refused_in_one_line():
    with pytest.raises(InputError) as e:
        SessionConfig(camera_optics="fisheye").validate()
    assert "photo" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(InputError) as e:
        SessionConfig(camera="device:0", camera_optics="photo").validate()
    assert "camera='sim'" in str(e.value)
    for name in PRESETS:
        SessionConfig(camera_optics=name).validate()
    SessionConfig().validate()                      # unset: the simple render


def _one_frame(tmp_path, optics):
    from monotracker.sim.phantom import default_phantom

    s = Session(SessionConfig(home=tmp_path / str(optics), clock="sim", camera_optics=optics))
    try:
        ph = default_phantom()
        for c in ph.fiducial_centres_lps:
            assert s.add_fiducial(c, ph.fiducial_radius_mm).ok
        assert s.confirm_fiducials().ok and s.use_sample_plan().ok
        assert s.start_camera().ok
        s.advance(0.1)
        rig = s._loop.camera.rig
        return rig.cam.optics, rig.latest_frame()[0]
    finally:
        s.shutdown()


def test_photo_preset_reaches_the_rendered_frames(tmp_path):
    optics, img = _one_frame(tmp_path, "photo")
    assert optics == PRESETS["photo"]
    plain_optics, plain = _one_frame(tmp_path, None)
    assert plain_optics is None
    assert img.shape == plain.shape
    # evidence in the pixels: surgical drapes (blue, teal, green-blue: blue channel over red)
    # fill the background of the photo-like frame, not of the simple render
    drape = lambda im: np.mean(im[:40, :40, 0].astype(float) - im[:40, :40, 2])
    assert drape(img) > 30 and drape(img) > drape(plain) + 20
