"""Learned (ONNX) detector vs the simulator's truth; the shipped model must be small."""

import numpy as np
import pytest

from monotracker.errors import InputError
from monotracker.sim.camera_sim import Occluder, SceneEvents, SimulatedCamera, Stray, _finger
from monotracker.vision.detect_learned import LearnedDetector, default_model_path


@pytest.fixture(scope="module")
def learned():
    return LearnedDetector()


def test_model_is_shipped_and_small():
    p = default_model_path()
    assert p.is_file() and p.stat().st_size < 3_000_000


def test_finds_all_balls_to_subpixel(learned, sim_still):
    img, tr = sim_still.render(0.5)
    d = learned.detect(img)
    assert len(d.fiducials) == 9
    err = np.linalg.norm(d.centres[:, None] - tr.ellipse_centres_px[None], axis=2).min(1)
    assert err.max() < 0.3


def test_ignores_round_green_strays_and_half_hidden_balls(learned, sim_still):
    px = sim_still.rest_projection()
    k = 3
    oc = Occluder(0.0, 10.0, _finger(60, 900, 0.0), px[k] + [300, 0], px[k], sweep_s=0.0)
    strays = [Stray(0, 5, (200.0, 150.0), 8.5, "round"), Stray(0, 5, (900.0, 300.0), 14.0, "irregular", 3)]
    cam = SimulatedCamera(events=SceneEvents(occluders=[oc], strays=strays), seed=0)
    img, tr = cam.render(1.0)
    d = learned.detect(img)
    err = np.linalg.norm(d.centres[:, None] - tr.ellipse_centres_px[None], axis=2)
    assert err.min(1).max() < 0.3                      # every detection is a real ball
    assert set(err.argmin(1)) == set(np.where(tr.visible)[0])
    assert k not in set(err.argmin(1))


def test_missing_model_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="train_segmenter"):
        LearnedDetector(model_path=tmp_path / "none.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    with pytest.raises(InputError, match="cannot load"):
        LearnedDetector(model_path=bad)


def test_lone_weak_cell_does_not_crash(learned, monkeypatch):
    """A single output cell just over the threshold vanishes when upsampled (regression)."""
    prob = np.zeros((180, 320), np.float32)
    prob[90, 160] = 0.51
    monkeypatch.setattr(learned, "probability", lambda image: prob)
    d = learned.detect(np.full((720, 1280, 3), 100, np.uint8))
    assert d.fiducials == []


def test_refuses_rings_and_empty_frames(learned, monkeypatch):
    """A frame with nothing, and a network output of rings, give a one-line refusal, no balls."""
    d = learned.detect(np.full((720, 1280, 3), 90, np.uint8))
    assert d.fiducials == [] and "no balls" in d.refusal
    import cv2

    img = np.full((720, 1280, 3), (120, 95, 60), np.uint8)
    prob = np.zeros((180, 320), np.float32)
    for cx in (80, 160, 240):
        cv2.circle(img, (4 * cx, 360), 40, (40, 160, 45), -1)       # big green balls
        cv2.circle(prob, (cx, 90), 10, 1.0, 3)                     # ... seen as rings
    monkeypatch.setattr(learned, "probability", lambda image: prob)
    d = learned.detect(img)
    assert d.fiducials == [] and "ring" in d.refusal
