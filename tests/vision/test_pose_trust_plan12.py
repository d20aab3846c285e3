"""Trust on a frame whose balls AND camera are the layout planner's own (issue 28;
``scripts/render_planned.py --plan-balls 12``): one full Mitsuba tuning scene committed in
tests/data/pbr_plan12/tuning (a clutter scene: gloves, an instrument, hair; streamed under the
``clutter`` condition: 1.5 px defocus, Bayer, noise, JPEG 85), streamed through the product's
PoseTracker as a still head, each pose judged against the scene's own geometry (the 80 mm deep
target). Where the product recommends the setup, a trusted pose must be right."""

from __future__ import annotations

import pytest

from monotracker.registration.report import tre_mm
from monotracker.sim.pbr.frameset import camera_frames, committed_root, list_scenes
from monotracker.vision.frames import Frame
from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig


@pytest.fixture(scope="module")
def scene():
    scenes = list_scenes(committed_root().parent / "pbr_plan12" / "tuning")
    assert len(scenes) == 1 and scenes[0].spec.split == "tuning" and scenes[0].spec.kind == "clutter"
    assert len(scenes[0].spec.fiducials_ct) == 12
    return scenes[0]


def _trusted(scene, config) -> list:
    tr = scene.truth
    trk = PoseTracker(tr.fiducials_ct, scene.camera_model(), radius_mm=tr.radius_mm, target_ct=tr.target_ct,
                      config=config)
    out = []
    for k, img in enumerate(camera_frames(scene, "clutter", 8)):
        e = trk.process(Frame(img, k / 30.0, k, None))
        if e.ok:
            out.append(float(tre_mm(e.T_cam_ct, tr.T_cam_ct, tr.target_ct)[0]))
    return out


def test_the_planners_layout_never_has_a_trusted_pose_over_2mm(scene):
    """The issue's hard limit holds on this frame with the default trust and the opt-in size
    cover; the default does trust poses here (3 of 8 frames when written)."""
    default = _trusted(scene, TrackerConfig())
    assert len(default) >= 2, default
    assert all(e <= 2.0 for e in default), default
    assert all(e <= 2.0 for e in _trusted(scene, TrackerConfig(edge_size_per_excess=1.0)))


@pytest.mark.xfail(strict=True, reason="issue 28 open: on the planner's own 12-ball layout the default trusts "
                   "frames 1.40 and 1.80 mm off (predicted 0.58-0.69 mm): blurred frame, dark hair and shadows "
                   "round whole balls, every outline 0.25-0.64 px too large, centres 0.4-1.1 px off "
                   "(docs/vision.md, 'The planner's own layouts rendered')")
def test_the_planners_layout_has_no_trusted_pose_over_1mm(scene):
    """The goal: within 1 mm whenever trusted. Fails today (strict xfail: it says so when it
    passes); the opt-in size cover (edge_size_per_excess 1.0) passes here but not on the held-out
    planner layouts (docs/vision.md)."""
    errs = _trusted(scene, TrackerConfig())
    assert all(e <= 1.0 for e in errs), errs


def _through_the_gate(scene, n_frames: int) -> tuple[int, list]:
    """(frames the tracker trusted, errors at the target (mm) of the poses the session's gate
    trusted) over a still-head stream of ``n_frames`` frames."""
    from monotracker.engine.config import SessionConfig
    from monotracker.engine.loop.gate import PoseGate
    from monotracker.engine.rigs.base import estimate_to_sample

    tr = scene.truth
    trk = PoseTracker(tr.fiducials_ct, scene.camera_model(), radius_mm=tr.radius_mm, target_ct=tr.target_ct)
    gate = PoseGate.from_config(SessionConfig())
    tracker_trusted, gate_errs = 0, []
    for k, img in enumerate(camera_frames(scene, "clutter", n_frames)):
        e = trk.process(Frame(img, k / 30.0, k, None))
        tracker_trusted += bool(e.ok)
        v = gate.check_sample(estimate_to_sample(e, list(range(len(tr.fiducials_ct)))))
        if v.trusted:
            gate_errs.append(float(tre_mm(e.T_cam_ct, tr.T_cam_ct, tr.target_ct)[0]))
    return tracker_trusted, gate_errs


def test_the_sessions_gate_lets_none_of_them_move_the_arm(scene):
    """What the arm follows: the tracker's poses through the session's gate (engine.loop.gate,
    default SessionConfig: 3 consecutive agreeing estimates after a cold start or refusals). In
    the first 8 frames the wrong frames above stand alone (trust flags ..T..T.T when written):
    none is the gate's. A longer stream is another matter (below)."""
    tracker_trusted, gate_errs = _through_the_gate(scene, 8)
    assert tracker_trusted >= 2
    assert all(err <= 1.0 for err in gate_errs), gate_errs


@pytest.fixture(scope="module")
def second_through_the_gate(scene) -> list:
    """The errors (mm) of the poses the gate trusted over 30 frames (1 s at 30 fps), streamed
    once for both tests below."""
    return _through_the_gate(scene, 30)[1]


def test_over_a_second_of_stream_the_gate_passes_no_pose_over_2mm(second_through_the_gate):
    """The hard limit through the gate over 30 frames (1 s at 30 fps): the gate does trust poses
    here, and none is over 2 mm."""
    gate_errs = second_through_the_gate
    assert len(gate_errs) >= 3, gate_errs
    assert all(err <= 2.0 for err in gate_errs), gate_errs


@pytest.mark.xfail(strict=True, reason="issue 28 open: over 30 frames the tracker trusts runs of 3 or more "
                   "agreeing frames 1-2 mm off here and the gate, which checks agreement (5 mm / 3 deg), passes "
                   "them; their error is a bias that changes across the layout, which the trust model covers "
                   "only in part (docs/vision.md, 'Longer streams')")
def test_over_a_second_of_stream_the_gate_passes_no_pose_over_1mm(second_through_the_gate):
    """The goal for what moves the arm: within 1 mm whenever the gate trusts it, however long
    the stream. Fails today (strict xfail: it says so when it passes)."""
    gate_errs = second_through_the_gate
    assert all(err <= 1.0 for err in gate_errs), gate_errs
