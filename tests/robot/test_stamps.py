"""Capture stamps of target poses: a re-sent, out-of-order, future-stamped or too-old pose must
never keep the arm moving (the staleness clock runs on the capture stamps, not on arrivals)."""

import numpy as np

from robot_rig import RATE, Rig, offset_target, ready_tip_pose, to_mm


def _tracking_rig():
    rig = Rig()
    T = offset_target((0.05, 0.0, 0.0), 0.0)
    rig.start(T)
    rig.run(0.2, T)
    assert rig.tracker.state.value == "tracking"
    return rig, T


def test_resent_frame_does_not_count_as_fresh():
    """The camera froze but the pose source keeps re-sending its last pose with the same
    capture stamp: the tracker must hold within stale_s, as if nothing arrived."""
    rig, T = _tracking_rig()
    stamp = rig.clock()
    cfg = rig.tracker.safety.cfg
    held_at = None
    for _i in range(int(0.3 * RATE)):
        rig.tracker.set_target(to_mm(T), stamp)
        rig.tracker.step()
        if held_at is None and rig.tracker.state.value == "holding":
            held_at = rig.clock() - stamp
        rig.clock.advance(1.0 / RATE)
        rig.arm.advance_to(rig.clock())
    assert held_at is not None, "kept tracking on a frozen pose stream"
    assert held_at <= cfg.stale_s + 1.5 / RATE


def test_future_stamp_is_rejected_and_holds():
    rig, T = _tracking_rig()
    r = rig.tracker.set_target(to_mm(T), rig.clock() + 5.0)
    assert not r.ok and "future" in r.reason
    assert rig.tracker.state.value == "holding"
    # the fault needs the operator: valid poses alone do not resume
    rig.run(0.1, T)
    assert rig.tracker.state.value == "holding"
    assert rig.tracker.start_tracking().ok


def test_out_of_order_pose_is_ignored():
    rig, T = _tracking_rig()
    now = rig.clock()
    assert rig.tracker.set_target(to_mm(T), now).ok
    older = T.copy()
    older[:3, 3] += [0.0, 0.005, 0.0]
    r = rig.tracker.set_target(to_mm(older), now - 0.05)
    assert not r.ok and "older" in r.reason
    assert np.allclose(rig.tracker.safety.target, T)
    assert rig.tracker.state.value == "tracking"  # out of order is not a fault by itself


def test_capture_age_is_checked_every_cycle_not_only_on_arrival():
    """Poses arrive often enough (every 48 ms) but each is 0.47 s old: between arrivals the
    newest capture becomes older than max_latency_s (0.5 s), and the arm must not move on it."""
    rig, T = _tracking_rig()
    cfg = rig.tracker.safety.cfg
    lat = cfg.max_latency_s - 0.03
    ages_while_tracking = []
    for i in range(int(1.0 * RATE)):
        now = rig.clock()
        if i % 6 == 0:
            rig.tracker.set_target(to_mm(T), now - lat)
        s = rig.tracker.step()
        if s.state == "tracking":
            ages_while_tracking.append(now - rig.tracker.safety.target_stamp)
        rig.clock.advance(1.0 / RATE)
        rig.arm.advance_to(rig.clock())
    assert max(ages_while_tracking) <= cfg.max_latency_s + 1e-9


def test_start_tracking_refuses_an_old_capture():
    rig = Rig()
    rig.tracker.connect()
    rig.tracker.arm()
    rig.clock.advance(10.0)
    T = ready_tip_pose()
    assert rig.tracker.set_target(to_mm(T), rig.clock() - 0.45).ok
    rig.clock.advance(0.08)  # arrived 80 ms ago (within stale_s) but captured 0.53 s ago
    assert not rig.tracker.start_tracking().ok


def test_control_clock_going_backwards_estops():
    """A control clock that runs backwards makes every age negative (stale targets would look
    fresh): latch an e-stop rather than keep moving on it."""
    rig, T = _tracking_rig()
    now = rig.clock()
    rig.tracker.step(now)
    stops = rig.arm.stops
    rig.tracker.step(now - 0.5)
    assert rig.tracker.state.value == "estopped"
    assert "backwards" in rig.tracker.safety.history[-1].reason
    assert rig.arm.stops > stops


def test_control_clock_jumping_forward_holds_on_the_stale_target():
    rig, T = _tracking_rig()
    rig.tracker.step(rig.clock() + 1.0)
    assert rig.tracker.state.value == "holding"


def test_reset_forgets_the_old_target():
    """After an e-stop reset, tracking needs a pose received after the reset, not one that was
    fresh before it (here: the clock went backwards, so the old pose's stamps lie ahead)."""
    rig, T = _tracking_rig()
    now = rig.clock()
    rig.tracker.step(now - 0.5)
    assert rig.tracker.reset().ok and rig.tracker.arm().ok
    assert not rig.tracker.start_tracking().ok  # the pre-reset pose does not count
    assert rig.tracker.set_target(to_mm(T), now - 0.5).ok  # new poses on the new clock are taken
    assert rig.tracker.start_tracking().ok
