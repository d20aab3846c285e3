"""Trust on physically rendered frames (issue 28 item 3): the committed Mitsuba tuning crops
(tests/data/pbr, no renderer needed) streamed through the product's PoseTracker as a still head,
each pose judged against the scene's own geometry (``truth.T_cam_ct``, the 80 mm deep target)."""

from __future__ import annotations

import numpy as np
import pytest

from monotracker.registration.report import tre_mm
from monotracker.sim.pbr.frameset import CONDITIONS, camera_frames, committed_root, list_scenes
from monotracker.vision.frames import Frame
from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig

N_FRAMES = 8


@pytest.fixture(scope="module")
def scenes():
    return list_scenes(committed_root() / "tuning")


def _stream(scene, condition, config):
    """(trusted?, error at the target mm, predicted TRE mm) per frame."""
    tr = scene.truth
    trk = PoseTracker(tr.fiducials_ct, scene.camera_model(), radius_mm=tr.radius_mm, target_ct=tr.target_ct,
                      config=config)
    out = []
    for k, img in enumerate(camera_frames(scene, condition, N_FRAMES)):
        e = trk.process(Frame(img, k / 30.0, k, None))
        out.append((bool(e.ok), float(tre_mm(e.T_cam_ct, tr.T_cam_ct, tr.target_ct)[0]) if e.ok else np.nan,
                    float(e.predicted_tre_mm)))
    return out


def _trusted_errors(scenes, config):
    errs = []
    for cond, c in CONDITIONS.items():
        for s in (x for x in scenes if x.spec.kind == c["kind"]):
            errs += [e for ok, e, _ in _stream(s, cond, config) if ok]
    return np.array(errs)


def test_no_trusted_pose_is_wrong_on_rendered_frames(scenes):
    """Every condition, every committed scene, 8 frames each: no trusted pose is more than 1 mm
    off at the target with the calibrated trust model, and it still trusts poses. (With the
    detector of 0d028e0 the per-frame model passes this on these crops too; with the detector
    before it, it trusted a pose 1.27 mm off here: the held-out figures are in the notes.)"""
    calibrated = _trusted_errors(scenes, TrackerConfig(centre_bias="detector"))
    assert len(calibrated) >= 1, "the calibrated model must still trust a pose"
    assert np.all(calibrated <= 1.0), np.sort(calibrated)[-5:]
