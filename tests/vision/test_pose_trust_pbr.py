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
    off at the target, with the product's per-frame trust model (which still trusts poses
    here) or with the calibrated one. (The calibrated model used to trust some of these; since
    it covers the bias that changes across the layout, measured on Mitsuba's and Blender's
    tuning frames, it trusts none of the committed crops: its reach is in the notes.)"""
    per_frame = _trusted_errors(scenes, TrackerConfig())
    assert len(per_frame) >= 1, "the product's trust model must still trust a pose on rendered frames"
    assert np.all(per_frame <= 1.0), np.sort(per_frame)[-5:]
    calibrated = _trusted_errors(scenes, TrackerConfig(centre_bias="detector"))
    assert np.all(calibrated <= 1.0), np.sort(calibrated)[-5:]


