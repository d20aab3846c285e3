"""A computer too slow for the pose pipeline says so (``pipeline_overloaded``, engine/loop/load.py)
instead of a ``pose_stale`` that reads like a camera fault; on the simulated clock, where each
estimate's cost is its measured thread CPU time (so the test does not depend on the machine's
speed or load: the slow estimator burns a fixed amount of its own CPU time)."""

import time

import numpy as np

from monotracker.engine.rigs.factory import build_camera_rig

from .conftest import plan_sample


def _slow(burn):
    """A camera factory whose rig spends ``burn["s"]`` more thread CPU time on every estimate."""

    def factory(source, calibration_path, plan, cfg, session):
        rig = build_camera_rig(source, calibration_path, plan, cfg, session)
        estimate = rig.estimate

        def slow_estimate(frame):
            c0 = time.thread_time()
            while time.thread_time() - c0 < burn["s"]:
                pass
            return estimate(frame)

        rig.estimate = slow_estimate
        return rig
    return factory


def _track(make_session, cpu_s, seconds=2.0, factory=None, marks=None):
    """Track the sample plan, then make every estimate cost ``cpu_s`` more (``factory``: how,
    default :func:`_slow`) for ``seconds``; (session, alerts). ``marks`` (a dict), if given, gets
    ``"commands_before"``: the count of control commands when the extra cost began."""
    burn = {"s": 0.0}
    factory = factory or _slow
    # freeze_after_s 0.3: on the simulated clock frames arriving while the estimator is busy are
    # not noted, so a gap over 0.1 s (a ~70 ms estimate, or a loaded machine's slower CPU time)
    # would read as a frozen camera first; this test is about the pipeline's own verdict
    s = make_session(clock="sim", camera="sim-points", camera_factory=factory(burn), freeze_after_s=0.3)
    plan_sample(s)
    assert s.start_camera().ok
    s.advance(0.5)
    assert s.arm("1234").ok and s.start_tracking().ok
    s.advance(0.5)
    if marks is not None:
        marks["commands_before"] = len(s.latencies_s())
    burn["s"] = cpu_s      # the machine gets busy while tracking
    s.advance(seconds)
    return s, [a for a in s.snapshot().alerts]


def test_a_pipeline_slower_than_the_camera_holds_with_its_own_alarm(make_session):
    # 80 ms per estimate at 30 fps: two frames in three dropped, poses ~190 ms old before the next
    s, alerts = _track(make_session, 0.080)
    codes = [a.code for a in alerts]
    assert "pipeline_overloaded" in codes and "pose_stale" not in codes and "camera_freeze" not in codes, sorted(set(codes))
    msg = next(a.message for a in alerts if a.code == "pipeline_overloaded")
    assert "too slow for the pose pipeline" in msg and "the camera itself delivers frames" in msg
    assert s.snapshot().robot.state == "holding"


def test_a_pipeline_that_keeps_up_raises_nothing(make_session):
    s, alerts = _track(make_session, 0.010)
    codes = [a.code for a in alerts]
    assert "pipeline_overloaded" not in codes and "pose_stale" not in codes, codes
    assert s.snapshot().robot.state == "tracking"


def test_late_frames_from_the_camera_stay_pose_stale(make_session):
    """Frames that reach the computer late (the camera's transport, not the computer's compute)
    are not the pipeline's overload."""
    s = make_session(clock="sim", camera="sim-points")
    plan_sample(s)
    assert s.start_camera().ok
    s.advance(0.5)
    assert s.arm("1234").ok and s.start_tracking().ok
    s.advance(0.5)
    s._loop.camera.rig.transport_delay_s = 0.25
    s.advance(1.0)  # past pose_stale's 0.5 s dwell (engine/alarms.py)
    codes = [a.code for a in s.snapshot().alerts]
    assert "pose_stale" in codes and "pipeline_overloaded" not in codes, sorted(set(codes))


def _after(burn):
    """A camera factory whose rig spends ``burn["s"]`` of thread CPU time after each pose was
    given out (as a due frame's camera-motion check does, ``CameraRig.after_publish``)."""

    def factory(source, calibration_path, plan, cfg, session):
        rig = build_camera_rig(source, calibration_path, plan, cfg, session)
        after = rig.after_publish

        def slow_after_publish():
            c0 = time.thread_time()
            while time.thread_time() - c0 < burn["s"]:
                pass
            return after()

        rig.after_publish = slow_after_publish
        return rig
    return factory


def test_work_after_the_pose_keeps_the_estimator_busy(make_session):
    """The simulated clock charges the work run after a pose to the estimator's time, not to the
    pose: 150 ms after every frame drops four frames in five, so poses come every ~170 ms and go
    stale, and the pipeline says it is the cause (its own alarm, the arm holds), as for 150 ms on
    the estimate itself."""
    s, alerts = _track(make_session, 0.150, factory=_after)
    codes = [a.code for a in alerts]
    assert "pipeline_overloaded" in codes and "pose_stale" not in codes, sorted(set(codes))
    assert s.snapshot().robot.state == "holding"


def _after_with_even_estimates(burn, estimate_s=0.006):
    """:func:`_after`, with every estimate padded to ``estimate_s`` of thread CPU time (more if it
    took more). The latency is quantised by the 8 ms control period: a frame captured on a tick
    is ready 30 ms (the sim camera's transport) + the estimate later, used at +32 ms below 2 ms
    of estimate, at +40 ms up to 10 ms. The sim-points estimate's own CPU time is ~2-4 ms, near
    the first step on a fast machine, so two runs could differ by its jitter alone (seen: one pose
    at 32 ms instead of 40 in a CI run); 6 ms sits 4 ms from either step."""
    after = _after(burn)

    def factory(*args):
        rig = after(*args)
        estimate = rig.estimate

        def even_estimate(frame):
            c0 = time.thread_time()
            sample = estimate(frame)
            while time.thread_time() - c0 < estimate_s:
                pass
            return sample

        rig.estimate = even_estimate
        return rig
    return factory


def test_work_after_the_pose_that_fits_the_frame_costs_the_pose_nothing(tmp_path):
    """15 ms after every pose (a camera-motion check takes ~3 ms) fits the 33 ms frame period:
    the same capture -> command latencies as without it (the latency is quantised by the 8 ms
    control period; the same ticks), the same poses used, no alarm. Truth: the same session
    without it (each in its own session folder). Every estimate costs the same 6 ms of CPU in
    both (:func:`_after_with_even_estimates`), so only the after-work differs between them."""
    from monotracker.engine import Session, SessionConfig

    lat, used = {}, {}
    for cpu_s in (0.0, 0.015):
        made = []

        def make(made=made, home=tmp_path / f"home{cpu_s}", **kw):
            factories = {k: kw.pop(k) for k in ("camera_factory", "robot_factory") if k in kw}
            made.append(Session(SessionConfig(home=home, **kw), **factories))
            return made[-1]

        try:
            marks = {}
            s, alerts = _track(make, cpu_s, factory=_after_with_even_estimates, marks=marks)
            assert "pipeline_overloaded" not in [a.code for a in alerts] and s.snapshot().robot.state == "tracking"
            lat[cpu_s] = [round(v * 1000) for v in s.latencies_s()[-40:]]
            # poses used while the after-work ran (not before it: the first estimates of a fresh
            # worker process can pay a one-off cost that the clock charges, so when tracking first
            # locks can differ between the two runs; seen once in CI: 61 against 76 in all), and
            # the newest one's capture
            used[cpu_s] = (len(s.latencies_s()) - marks["commands_before"], s.snapshot().pose.t)
        finally:
            for m in made:
                m.shutdown()
    # the same latencies but on at most 2 of the 40: an estimate whose thread CPU under a loaded
    # host exceeds its 6 ms pad is charged more in either run (seen in fresh-clone CIs: one pose at
    # 48 ms instead of 40 at load 3.5; one at 72 ms, 2026-12-01, a one-off 32 ms of thread CPU in
    # the run with the after-work, all 39 others equal). Charging the 15 ms after-work to the pose
    # moves every latency (56 ms), which the median and the count still refuse.
    a, b = np.array(lat[0.0]), np.array(lat[0.015])
    assert len(a) == len(b) and np.median(a) == np.median(b), lat
    assert np.count_nonzero(a != b) <= 2, lat
    # the same newest capture; the count of poses used may differ by one (a loaded host's one-off
    # spike drops a pose in either run: seen in a fresh-clone CI, 2026-12-01, 59 against 60)
    assert used[0.015][1] == used[0.0][1] and abs(used[0.015][0] - used[0.0][0]) <= 1, used
