"""One trust verdict: the per-frame rules every camera rig applies come from the session's
configuration (``min_fiducials`` reaches vision), and the point-level twin ("sim-points") is
judged by the same rules as the image rigs (it used to skip them: registration alone)."""

import pytest

from monotracker.engine import SessionConfig
from monotracker.engine.loop.gate import PoseGate
from monotracker.engine.plan import load_plan
from monotracker.errors import InputError
from monotracker.engine.rigs.sim import ProjectedFiducialRig

from .conftest import plan_sample


@pytest.mark.parametrize("camera", ["sim-points", "sim"])
def test_min_fiducials_and_the_tre_limit_reach_every_rigs_pose_tracker(make_session, camera):
    s = make_session(clock="sim", camera=camera, min_fiducials=3, max_predicted_tre_mm=0.8,
                     tre_confidence=0.9, sim_camera_process=False)
    plan_sample(s)
    assert s.start_camera().ok
    s.advance(0.2)  # the sim-points rig builds its tracker at its first estimate
    tracker = s._loop.camera.rig.tracker
    assert tracker is not None
    assert tracker.config.min_fiducials == 3 == s._loop.gate.min_fiducials
    assert tracker.config.max_predicted_tre_mm == 0.8 == s._loop.gate.max_predicted_tre_mm
    assert tracker.config.right_mm == 0.8 and abs(tracker.config.max_not_right_probability - 0.1) < 1e-12


def test_frame_rules_follow_the_session_configuration():
    cfg = SessionConfig(min_fiducials=5, max_predicted_tre_mm=0.7)
    rules = cfg.frame_rules()
    gate = PoseGate.from_config(cfg)
    assert (rules.min_fiducials, rules.max_predicted_tre_mm) == (5, 0.7)
    assert (gate.frame_rules.min_fiducials, gate.frame_rules.max_predicted_tre_mm) == (5, 0.7)
    assert cfg.frame_rules() is not rules  # each rig gets its own


def test_the_tre_confidence_setting_reaches_the_frame_rules_and_bad_values_are_refused():
    """``tre_confidence`` 0.95: trusted only within the session's TRE limit at 95 % (vision's
    ``right_mm`` is that limit, ``max_not_right_probability`` 0.05); off (0) by default."""
    rules = SessionConfig().frame_rules()
    assert rules.max_not_right_probability == 1.0
    rules = SessionConfig(max_predicted_tre_mm=0.8, tre_confidence=0.95).frame_rules()
    assert rules.right_mm == 0.8 and abs(rules.max_not_right_probability - 0.05) < 1e-12
    SessionConfig(tre_confidence=0.95).validate()
    for bad in (0.3, 1.0, -0.1, True, "0.95"):
        with pytest.raises(InputError, match="tre_confidence"):
            SessionConfig(tre_confidence=bad).validate()


def test_the_ball_finish_setting_reaches_the_frame_rules_and_bad_values_are_refused():
    """``ball_finish`` (what the team says of the kit's balls) reaches vision's per-frame rules
    (``TrackerConfig.ball_finish``: the glossy frames' wider cover); each frame's reading by
    default; a value outside vision's vocabulary is refused in one line."""
    assert SessionConfig().frame_rules().ball_finish == "read"
    for finish in ("read", "matte", "glossy"):
        cfg = SessionConfig(ball_finish=finish)
        cfg.validate()
        assert cfg.frame_rules().ball_finish == finish
    for bad in ("shiny", "", None, 1):
        with pytest.raises(InputError, match="ball finish must be one of read, matte, glossy"):
            SessionConfig(ball_finish=bad).validate()


def test_point_twin_refuses_what_the_image_rigs_would(tmp_path, make_session):
    """Noisy points (0.5 px): poses whose predicted error at the target is under the 1 mm limit
    but whose error may exceed 2 mm too often are refused by the rig (vision's tail rule), as an
    image rig refuses them; before, the point twin handed them on as good poses."""
    s = make_session(clock="sim")
    plan_sample(s)
    plan = load_plan(s.plan_path)
    s.shutdown()
    rig = ProjectedFiducialRig(plan, trajectory="still", seed=3, noise_px=0.5, rules=SessionConfig().frame_rules())
    samples = [rig.estimate(rig.capture(k / 30.0)) for k in range(40)]
    tail = [smp for smp in samples if smp.code == "tre_limit" and smp.predicted_tre_mm is not None
            and smp.predicted_tre_mm < 1.0]
    assert tail, [(smp.ok, smp.code, smp.predicted_tre_mm) for smp in samples]
    assert all(not smp.ok and smp.T_cam_ct is None for smp in tail)
    # the same points at the image detector's noise pass
    rig = ProjectedFiducialRig(plan, trajectory="still", seed=3, noise_px=0.1, rules=SessionConfig().frame_rules())
    samples = [rig.estimate(rig.capture(k / 30.0)) for k in range(40)]
    assert sum(smp.ok for smp in samples[10:]) == 30, [(smp.ok, smp.code) for smp in samples]
    assert max(smp.truth_tre_mm for smp in samples[10:]) < 0.5


def test_the_still_view_mean_is_opt_in_reaches_the_image_rigs_tracker_and_bad_values_are_refused(make_session):
    """``average_still_frames`` (the detector reads the mean of a still view's frames, vision's
    ``TrackerConfig.average_still_frames``): off by default, the number of frames reaches the
    image rig's tracker, and a value that is not a whole number from 0 to 30 is refused."""
    assert SessionConfig().frame_rules().average_still_frames == 0
    assert SessionConfig(average_still_frames=8).frame_rules().average_still_frames == 8
    for bad in (-1, 31, 2.5, True, "8"):
        with pytest.raises(InputError, match="average_still_frames"):
            SessionConfig(average_still_frames=bad).validate()
    s = make_session(clock="sim", camera="sim", average_still_frames=6, sim_camera_process=False, trajectory="still")
    plan_sample(s)
    assert s.start_camera().ok
    s.advance(0.2)
    tracker = s._loop.camera.rig.tracker
    assert tracker.still_frames is not None and tracker.still_frames.max_frames == 6
    assert tracker.still_frames.n >= 1          # it reads frames
    # the twin's camera is quieter than the mean's noise limit: its frames are read alone ...
    assert s.snapshot().pose.averaged_frames == 1
    # ... and with the limit off, the still head's poses come from the mean, and the snapshot
    # (what the screen shows, ui/status.averaged_note) says of how many frames
    tracker.still_frames.min_noise_dn = 0.0
    s.advance(0.5)
    assert s.snapshot().pose.averaged_frames == 6
