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
    """The issue's hard limit (no trusted pose over 2 mm) with either trust model; and the
    default does trust poses on these close frames (the camera stands 300-450 mm away)."""
    default = [e for s in planned for e in _trusted(s, TrackerConfig())]
    assert len(default) >= 3, default
    for config in (TrackerConfig(), TrackerConfig(centre_bias="detector")):
        errs = [e for s in planned for e in _trusted(s, config)]
        assert all(e <= 2.0 for e in errs), errs


@pytest.mark.xfail(strict=True, reason="known (2026-11-30): the default per-frame model trusts the clutter scene's frame 6 "
                   "1.39 mm off (predicted 0.58 mm; balls 0 and 1 whole but 0.64-0.69 px off at an edge RMS of "
                   "0.14-0.26 px) and the degraded scene's frame 6 1.24 mm off (predicted 0.68 mm; ball 7 whole but "
                   "1.44 px off at an edge RMS of 0.32 px): the per-ball tail, a whole ball's bias several times its "
                   "edge spread (and the RMS gate's own statistics: both are under 1 mm by their predictions' RMS). The "
                   "opt-in gate max_not_right_probability=0.05 refuses both, with most of the trust on the rendered "
                   "sets (docs/vision.md). Remove this mark when the trust model or the detector covers it.")
def test_planner_placed_frames_no_trusted_pose_over_1mm(planned):
    for config in (TrackerConfig(), TrackerConfig(centre_bias="detector")):
        errs = [e for s in planned for e in _trusted(s, config)]
        assert all(e <= 1.0 for e in errs), errs
