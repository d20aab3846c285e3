"""One operator in control: the PIN guard, taking/releasing control, view-only clients."""

import numpy as np

from monotracker.engine.access import NOT_IN_CONTROL, ClientSession, ControlArbiter, PinGuard

from .conftest import plan_sample
from .doubles import FollowerRobotRig, TruthCameraRig


# ---------------------------------------------------------------- PinGuard (pure)
def test_pin_guard_counts_wrong_tries_then_locks_out_and_doubles():
    g = PinGuard("2468")
    assert g.check("2468", 0.0).ok
    msgs = [g.check("0000", 1.0).message for _ in range(4)]
    assert msgs == [f"wrong PIN ({n} tr{'y' if n == 1 else 'ies'} left before a 30 s lockout)" for n in (4, 3, 2, 1)]
    r = g.check("1111", 2.0)  # 5th wrong try starts the lockout
    assert not r.ok and r.message == "PIN locked for 30 s after 5 wrong tries"
    assert g.locked_for(2.0) == 30.0
    # while locked, even the right PIN is refused, with the time left (rounded up)
    r = g.check("2468", 5.5)
    assert not r.ok and r.message == "PIN locked for 27 s after 5 wrong tries"
    assert g.locked_for(32.0) == 0.0
    # the next five wrong tries lock it for twice as long
    for _ in range(4):
        assert "before a 60 s lockout" in g.check("9", 40.0).message
    assert g.check("9", 40.0).message == "PIN locked for 60 s after 5 wrong tries"
    assert not g.check("2468", 99.0).ok and g.check("2468", 100.0).ok
    # a right PIN clears the count and the doubling
    assert "4 tries left before a 30 s lockout" in g.check("0", 101.0).message
    assert "2468" not in "".join(msgs)


def test_brute_force_of_the_whole_pin_space_is_impractical():
    """200 tries as fast as possible: at most 5 checked per lockout, and the right one is refused."""
    g = PinGuard("0199")
    accepted = [pin for pin in (f"{i:04d}" for i in range(200)) if g.check(pin, 10.0).ok]
    assert accepted == []
    assert g.locked_for(10.0) == 30.0


def test_arbiter_one_controller_at_a_time():
    a = ControlArbiter()
    assert a.controller is None and not a.is_controller("x")
    assert a.claim("x", "laptop", 1.0) == (None, "")
    assert a.claim("y", "tablet", 2.0) == ("x", "laptop")
    assert not a.release("x") and a.is_controller("y")
    assert a.summary(3.0).controller == "y" and a.summary(3.0).since == 2.0
    assert a.release("y") and a.controller is None


# ---------------------------------------------------------------- Session integration
def _tracking_ready(make_session):
    s = make_session(clock="sim", camera_factory=lambda *a: TruthCameraRig(),
                     robot_factory=lambda cfg, sess: FollowerRobotRig())
    plan_sample(s)
    return s


def test_second_client_is_view_only_but_can_stop(make_session):
    s = _tracking_ready(make_session)
    a, b = s.for_client("tab-a"), s.for_client("tab-b")
    assert isinstance(a, ClientSession)
    # nobody in control: neither tab may drive; the local operator (Session) may
    assert a.start_camera() == b.start_camera()
    assert not a.start_camera().ok and a.start_camera().message == NOT_IN_CONTROL
    assert not a.claim_control(pin="0000").ok
    assert a.claim_control(pin="1234", label="OR laptop").ok
    ctl = s.snapshot().control
    assert ctl.controller == "tab-a" and ctl.controller_label == "OR laptop" and ctl.pin_locked_s == 0
    assert a.start_camera().ok
    s.advance(0.5)
    assert a.arm("1234").ok
    assert a.start_tracking().ok
    s.advance(0.3)
    assert s.snapshot().robot.state == "tracking"
    # tab b: reads are the same, every command is refused ...
    assert b.snapshot().robot.state == "tracking" and b.latest_frame() is s.latest_frame()
    assert b.volume() is s.volume() and len(b.audit_entries()) == len(s.audit_entries())
    refused = [b.stop_tracking(), b.disarm(), b.arm("1234"), b.set_entry([0, 0, 0]), b.set_target([1, 2, 3]),
               b.new_plan(), b.unlock_fiducials(), b.stop_camera(), b.set_hand_eye(np.eye(4)),
               b.inject_fault("occlude-all"), b.reset_estop(), b.load_sample_ct(), b.use_sample_plan(),
               b.export_slicer_markups("/tmp"), b.start_tracking(), b.set_camera("sim")]
    assert all(not r.ok and r.message == NOT_IN_CONTROL for r in refused)
    assert s.snapshot().robot.state == "tracking"
    assert s.plan_copy().path_complete
    # ... except STOP, always
    assert b.estop().ok and s.snapshot().robot.state == "estopped"
    assert not b.reset_estop().ok and s.snapshot().robot.state == "estopped"
    assert a.reset_estop().ok and s.snapshot().robot.state == "disarmed"


def test_take_over_needs_the_pin_and_disconnect_releases(make_session):
    s = _tracking_ready(make_session)
    a, b = s.for_client("tab-a"), s.for_client("tab-b")
    assert s.claim_control("tab-a", "1234", "laptop").ok
    r = s.claim_control("tab-b", "4321", "tablet")
    assert not r.ok and "wrong PIN" in r.message and s.snapshot().control.controller == "tab-a"
    assert s.claim_control("tab-b", "1234", "tablet").ok
    assert s.snapshot().control.controller == "tab-b"
    assert not a.start_camera().ok and b.start_camera().ok
    # a client cannot release (or take) control for another
    assert not a.release_control("tab-b").ok
    assert s.release_control("tab-a").message == "not in control"
    assert s.snapshot().control.controller == "tab-b"
    assert s.release_control("tab-b").ok  # the UI calls this when tab b disconnects
    ctl = s.snapshot().control
    assert ctl.controller is None and ctl.since is None
    assert not b.stop_camera().ok
    codes = [e.code for e in s.audit_entries()]
    assert codes.count("control_taken") == 2 and "control_released" in codes and "control_refused" in codes


def test_wrong_pins_lock_arming_and_control_and_never_reach_the_log(make_session):
    s = _tracking_ready(make_session)
    assert s.start_camera().ok
    for _ in range(4):
        r = s.arm("wrong-9999")
        assert not r.ok and "wrong PIN" in r.message
    r = s.claim_control("tab-a", "wrong-8888")  # the same guard: the 5th wrong try locks both
    assert not r.ok and r.message == "PIN locked for 30 s after 5 wrong tries"
    snap = s.snapshot()
    assert snap.control.pin_locked_s == 30.0
    assert not s.arm("1234").ok and snap.robot.state == "disarmed"
    assert not s.claim_control("tab-a", "1234").ok
    # 200 more tries cannot flood the operator's alerts: one lockout alert for the episode
    for i in range(200):
        s.arm(f"{i:04d}")
    alerts = [e.code for e in s.snapshot().alerts]
    assert alerts.count("pin_lockout") == 1 and "arm_refused" not in alerts
    s.advance(30.1)
    assert s.snapshot().control.pin_locked_s == 0.0
    assert s.arm("1234").ok
    rows = s.audit_entries()
    assert sum(e.code == "arm_refused" for e in rows) == 4 + 1 + 200  # the right PIN while locked counts as a refused try too
    for e in rows:
        text = e.message + repr(getattr(e, "data", ""))
        assert "wrong-9999" not in text and "wrong-8888" not in text and "'1234'" not in text


def test_client_session_is_fail_closed_for_unknown_commands(make_session):
    s = make_session(clock="sim")
    c = s.for_client("x")
    # every public Session method that is not a known read is refused when not in control
    assert not c.advance(1.0).ok and not c.shutdown().ok
    try:
        c._loop  # noqa: B018 - private state is not reachable through the proxy
        raise AssertionError("private attribute reachable")
    except AttributeError:
        pass
    assert c.snapshot().control.controller is None and c.config.arm_pin == "****" and s.config.arm_pin == "1234"
