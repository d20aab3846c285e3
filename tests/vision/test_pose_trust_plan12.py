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


#: the default trust without the shading check (the default until 2026-12-01)
NO_CHECK = TrackerConfig(shading_check_factor=0.0)


def test_the_planners_layout_never_has_a_trusted_pose_over_2mm(scene):
    """The issue's hard limit holds on this frame with the default trust, the opt-in size cover,
    and the default without the shading check, which does trust poses here (3 of 8 frames when
    written)."""
    no_check = _trusted(scene, NO_CHECK)
    assert len(no_check) >= 2, no_check
    assert all(e <= 2.0 for e in no_check), no_check
    assert all(e <= 2.0 for e in _trusted(scene, TrackerConfig()))
    assert all(e <= 2.0 for e in _trusted(scene, TrackerConfig(edge_size_per_excess=1.0)))


def test_the_planners_layout_has_no_trusted_pose_over_1mm(scene):
    """Within 1 mm whenever trusted. Without the shading check the tracker trusted frames 1.40
    and 1.80 mm off here (predicted 0.58-0.69 mm: blurred frame, dark hair and shadows round whole
    balls, centres 0.4-1.1 px off; a strict xfail until 2026-12-01); the check refuses them (the
    balls' shading-corrected centres move the pose by more than half the limit at the target).
    It refuses every frame of this stream: the reach it costs (docs/vision.md, "The shading
    check")."""
    assert any(e > 1.0 for e in _trusted(scene, NO_CHECK))       # what the check has to catch
    errs = _trusted(scene, TrackerConfig())
    assert all(e <= 1.0 for e in errs), errs


def _through_the_gate(scene, n_frames: int, config=None) -> tuple[int, list]:
    """(frames the tracker trusted, errors at the target (mm) of the poses the session's gate
    trusted) over a still-head stream of ``n_frames`` frames (``config``: the tracker's; None the
    default)."""
    from monotracker.engine.config import SessionConfig
    from monotracker.engine.loop.gate import PoseGate
    from monotracker.engine.rigs.base import estimate_to_sample

    tr = scene.truth
    trk = PoseTracker(tr.fiducials_ct, scene.camera_model(), radius_mm=tr.radius_mm, target_ct=tr.target_ct,
                      config=config)
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
    default SessionConfig: 3 consecutive agreeing estimates after a cold start or refusals), in the
    first 8 frames: none over 1 mm with the default trust. Without the shading check the gate did
    pass none here either while the edge fit left only shadowed rays OUTSIDE the outline out (the
    wrong frames stood alone, trust flags ..T..T.T); with shadowed rays inside it left out too
    (``edge_fit.SHADOW_IN_PX``, the default since 2026-12-01) the unchecked tracker trusts a run of
    agreeing wrong frames and the gate passes one (1.75 mm when written): the check is what keeps
    it from the arm."""
    tracker_trusted, gate_errs = _through_the_gate(scene, 8, NO_CHECK)
    assert tracker_trusted >= 2
    assert any(err > 1.0 for err in gate_errs), gate_errs          # what the check has to catch
    assert all(err <= 1.0 for err in _through_the_gate(scene, 8)[1])


@pytest.fixture(scope="module")
def second_through_the_gate(scene) -> dict:
    """The errors (mm) of the poses the gate trusted over 30 frames (1 s at 30 fps), with the
    default trust and without its shading check, streamed once for the tests below."""
    return {"default": _through_the_gate(scene, 30)[1], "no check": _through_the_gate(scene, 30, NO_CHECK)[1]}


def test_over_a_second_of_stream_the_gate_passes_no_pose_over_2mm(second_through_the_gate):
    """The hard limit through the gate over 30 frames (1 s at 30 fps), with and without the
    shading check; without it the gate does trust poses here."""
    assert len(second_through_the_gate["no check"]) >= 3, second_through_the_gate
    assert all(err <= 2.0 for errs in second_through_the_gate.values() for err in errs), second_through_the_gate


def test_over_a_second_of_stream_the_gate_passes_no_pose_over_1mm(second_through_the_gate):
    """What moves the arm is within 1 mm whenever the gate trusts it. Without the shading check
    the tracker trusted runs of 3 or more agreeing frames 1-2 mm off here and the gate, which
    checks agreement (5 mm / 3 deg), passed them (12 poses, 1.04-1.96 mm, when written: a strict
    xfail until 2026-12-01; their error is a centre bias that changes across the layout,
    docs/vision.md "Longer streams"); with the check the gate passes none over 1 mm (none at all
    on this stream: the reach it costs)."""
    assert any(err > 1.0 for err in second_through_the_gate["no check"])      # what the check has to catch
    assert all(err <= 1.0 for err in second_through_the_gate["default"]), second_through_the_gate
