"""Trust on physically rendered frames with the camera where the layout planner places it
(issue 28; ``scripts/render_planned.py``): two full Mitsuba tuning frames committed in
tests/data/pbr_planned/tuning (their crops do not reproduce the case: a crop's sensor noise is
another draw), streamed through the product's PoseTracker as a still head, each pose judged
against the scene's own geometry (the 80 mm deep target)."""

from __future__ import annotations

import pytest

from monotracker.registration.report import tre_mm
from monotracker.sim.pbr.frameset import camera_frames, committed_root, list_scenes
from monotracker.vision.frames import Frame
from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig

#: each committed scene with the condition it is streamed under
CONDITION = {"clean": "degraded", "clutter": "clutter"}


@pytest.fixture(scope="module")
def planned():
    scenes = list_scenes(committed_root().parent / "pbr_planned" / "tuning")
    assert {s.spec.split for s in scenes} == {"tuning"} and len(scenes) == 2
    assert all(s.spec.index >= 5000 for s in scenes)          # render_planned.py's own index range
    return scenes


def _trusted(scene, config) -> list:
    tr = scene.truth
    trk = PoseTracker(tr.fiducials_ct, scene.camera_model(), radius_mm=tr.radius_mm, target_ct=tr.target_ct,
                      config=config)
    out = []
    for k, img in enumerate(camera_frames(scene, CONDITION[scene.spec.kind], 8)):
        e = trk.process(Frame(img, k / 30.0, k, None))
        if e.ok:
            out.append(float(tre_mm(e.T_cam_ct, tr.T_cam_ct, tr.target_ct)[0]))
    return out


def test_planner_placed_frames_are_trusted_and_never_over_2mm(planned):
    """The issue's hard limit (no trusted pose over 2 mm) with either trust model, with the
    remembered balls of a still head (the default, ``TrackerConfig.remember_frames``) and
    without, with the balls' finish read from the frame (the default) and with every frame read
    as matte (the default before 2026-12-01's twenty-fifth session).

    Read as matte these close frames (the camera 300-450 mm away) are trusted: without memory 2
    of the clutter scene's 8 (0.71-0.78 mm) since the edge fit also leaves shadowed rays inside
    the outline out; with the balls the last frames found 6 of 8 (0.71-1.05 mm), the frames that
    had 4-5 balls of their own now have 6. The clutter scene's balls are glossy beside contact
    shadows: with the finish read (:mod:`monotracker.vision.ball_gloss`) the wider few-ball
    cover refuses all of them (predicted 0.90-1.13 mm for poses 0.71-1.05 mm off: the matte
    reading predicted 0.55-0.75 mm, under the error); the degraded scene is trusted by neither."""
    matte_alone = [e for s in planned for e in _trusted(s, TrackerConfig(glossy_highlight_ratio=0.0, remember_frames=0))]
    matte = [e for s in planned for e in _trusted(s, TrackerConfig(glossy_highlight_ratio=0.0))]
    assert len(matte_alone) >= 2, matte_alone
    assert len(matte) >= len(matte_alone) + 2, (matte, matte_alone)
    for config in (TrackerConfig(), TrackerConfig(remember_frames=0), TrackerConfig(centre_bias="detector"),
                   TrackerConfig(glossy_highlight_ratio=0.0)):
        errs = [e for s in planned for e in _trusted(s, config)]
        assert all(e <= 2.0 for e in errs), errs


def test_planner_placed_frames_no_trusted_pose_over_1mm_each_frame_alone(planned):
    """Until 2026-11-30 (fifth session) the default trusted the clutter scene's frame 6 1.39 mm
    off (predicted 0.58 mm) and the degraded scene's frame 6 1.24 mm off (0.68 mm), both with 5
    balls whose errors the pose absorbed (a whole ball 0.6-1.4 px off at an edge RMS of
    0.14-0.32 px): the few-ball cover (``TrackerConfig.few_balls_cover``) refuses them. Each
    frame's own balls only (``remember_frames`` 0) and the pooled model."""
    for config in (TrackerConfig(remember_frames=0), TrackerConfig(centre_bias="detector")):
        errs = [e for s in planned for e in _trusted(s, config)]
        assert all(e <= 1.0 for e in errs), errs


def test_planner_placed_frames_no_trusted_pose_over_1mm(planned):
    """Known until 2026-12-01 (an xfail): with the remembered balls of a still head the clutter
    scene's frame 3 (since the twenty-first session frame 7) was trusted 1.05-1.06 mm off at a
    predicted 0.56-0.62 mm; its balls err 0.4-0.8 px in x on one side of the layout (contact
    shadows on +x), which no per-ball cover of the matte reading sees. Its balls are glossy:
    read so, the default refuses it; read as matte it is trusted again (what the reading buys)."""
    errs = [e for s in planned for e in _trusted(s, TrackerConfig())]
    assert all(e <= 1.0 for e in errs), errs
    matte = [e for s in planned for e in _trusted(s, TrackerConfig(glossy_highlight_ratio=0.0))]
    assert any(e > 1.0 for e in matte), matte
