"""The glossy frames' wider cover (issue 28, :mod:`monotracker.vision.ball_gloss`,
``TrackerConfig.glossy_highlight_ratio``) on our simulator's photo-like frames: specular balls
(Blinn-Phong highlights, ``Optics.ball_specular``) on skin with NO contact shadow, defocus,
sensor noise, JPEG, dim light (``benchmarks/camera_pipeline.py``'s ``degraded`` condition). The
balls read glossy, their centres are right (no shadow pushes an edge), and the default must trust
these frames exactly as the matte reading does; only the contact-shadow condition
(``glossy_needs_shadow``) keeps it so, which the last config shows by refusing more."""

from __future__ import annotations

import numpy as np
import pytest

from monotracker.registration.report import tre_mm
from monotracker.sim.camera_sim import SceneEvents, SimulatedCamera
from monotracker.sim.optics import PRESETS
from monotracker.sim.or_layout import default_layout
from monotracker.vision.ball_gloss import frame_highlight
from monotracker.vision.detect_classical import ClassicalDetector
from monotracker.vision.detection import BlobRules
from monotracker.vision.frames import Frame
from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig
from monotracker.vision.recording import RecordingDetector

N_FRAMES, SECONDS, SEED = 12, 10.0, 3


@pytest.fixture(scope="module")
def degraded():
    layout = default_layout()
    cam = SimulatedCamera(trajectory=layout.motion("breathing", seed=SEED), seed=SEED, optics=PRESETS["degraded"],
                          T_cam_world=layout.T_cam_ct0)
    cam.events = SceneEvents(lighting=[(0.0, 0.6), (SECONDS, 0.6)])
    times = np.linspace(0.0, SECONDS - 1e-3, N_FRAMES)
    return cam, times, [cam.render(t) for t in times]


def _stream(degraded, config):
    """Per frame: (trusted?, error at the target mm, the frame's highlight reading)."""
    cam, times, frames = degraded
    ph = cam.phantom
    det = RecordingDetector(ClassicalDetector(BlobRules(radius_mm=ph.fiducial_radius_mm, focal_px=float(cam.K[0, 0]),
                                            camera=cam.camera)))
    trk = PoseTracker(cam.fiducials_ct, cam.camera, detector=det, radius_mm=ph.fiducial_radius_mm,
                      target_ct=ph.sample_target_lps, config=config)
    out = []
    for i, (img, tr) in enumerate(frames):
        e = trk.process(Frame(img, float(times[i]), i, tr))
        err = float(tre_mm(e.T_cam_ct, tr.T_cam_ct, ph.sample_target_lps)[0]) if e.ok else np.nan
        out.append((bool(e.ok), err, frame_highlight([f.features for f in det.log[-1].fiducials])))
    return out


def test_specular_balls_without_contact_shadows_keep_the_default_cover(degraded):
    default = _stream(degraded, TrackerConfig())
    # the simulator's specular balls do read glossy: the cue alone would apply the wider cover
    highlights = [h for _ok, _e, h in default]
    assert np.nanmedian(highlights) >= TrackerConfig().glossy_highlight_ratio, highlights
    matte = _stream(degraded, TrackerConfig(glossy_highlight_ratio=0.0))
    assert [ok for ok, _e, _h in default] == [ok for ok, _e, _h in matte]
    trusted = [e for ok, e, _h in default if ok]
    assert len(trusted) >= N_FRAMES // 2 and max(trusted) < 1.0, trusted
    # without the contact-shadow condition the same right poses are refused
    no_shadow_test = _stream(degraded, TrackerConfig(glossy_needs_shadow=False))
    assert sum(ok for ok, _e, _h in no_shadow_test) < len(trusted), no_shadow_test
