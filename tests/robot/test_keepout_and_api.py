import time

import numpy as np

from monotracker.robot import kinematics as kin
from monotracker.robot.apff import APFFParams
from monotracker.robot.tracker import Tracker
from monotracker.robot.units import m_to_mm, mm_to_m, transform_m_to_mm, transform_mm_to_m
from robot_rig import Rig, ready_tip_pose, to_mm


def _keepout_rig(eta):
    rig = Rig(params=APFFParams(eta=eta))
    T0 = ready_tip_pose()
    centre = T0[:3, 3] + [0.0, 0.0, -0.10]
    radius = 0.095  # the tip starts 5 mm above the sphere
    assert rig.tracker.set_head_sphere(m_to_mm(centre), m_to_mm(radius), frame="base").ok
    T = T0.copy()
    T[:3, 3] += [0.04, 0.0, -0.03]  # inside the head, 40 mm to the side: not along the path
    rig.tracker.safety.cfg.jump_m = 0.1
    rig.start(T)
    snaps = rig.run(2.0, T)
    return rig, snaps, centre, radius, T


def _worst_penetration(snaps, centre, radius, T_target, rig):
    worst = 0.0
    for s in snaps:
        pts = rig.tracker.safety.needle_points(transform_mm_to_m(s.T_base_tool0_mm))
        d = np.linalg.norm(pts - centre, axis=1) - radius
        free = rig.tracker.corridor.contains(pts, T_target)
        worst = min(worst, float(np.min(np.where(free, 0.0, d))))
    return worst


def test_keepout_blocks_motion_into_head_off_path_even_without_repulsion():
    rig, snaps, c, r, T = _keepout_rig(eta=0.0)
    assert any(k == "warning" and "keep-out" in p for k, p in rig.events)
    assert _worst_penetration(snaps, c, r, T, rig) > -0.002  # at most braking distance
    assert snaps[-1].tip_error_mm > 20  # it did not go through the head to the target


def test_repulsion_keeps_needle_off_the_head():
    rig, snaps, c, r, T = _keepout_rig(eta=1e-5)
    assert _worst_penetration(snaps, c, r, T, rig) > -0.002


def test_along_the_planned_path_the_needle_may_enter():
    rig = Rig()
    T0 = ready_tip_pose()
    centre = T0[:3, 3] + [0.0, 0.0, -0.10]
    rig.tracker.set_head_sphere(m_to_mm(centre), 95.0, frame="base")
    T = T0.copy()
    T[:3, 3] += [0.0, 0.0, -0.01]  # 5 mm into the sphere, straight down the needle axis
    rig.start(T)
    snaps = rig.run(2.0, T)
    assert snaps[-1].tip_error_mm < 0.1
    assert not any(k == "warning" for k, _ in rig.events)


def test_head_sphere_in_target_frame_moves_with_target():
    rig = Rig()
    T = ready_tip_pose()
    rig.tracker.set_target(to_mm(T), 0.0)
    assert rig.tracker.set_head_sphere([0, 0, 100.0], 90.0).ok  # 100 mm ahead along the needle
    h = rig.tracker.head_sphere_base()
    assert np.allclose(h.centre_m, T[:3, 3] + 0.1 * T[:3, 2])
    assert not rig.tracker.set_head_sphere([0, 0, np.nan], 90).ok
    assert not rig.tracker.set_head_sphere([0, 0, 0], -1).ok
    assert not rig.tracker.set_head_sphere([0, 0, 0], 90, frame="ct").ok


def test_bad_targets_never_raise():
    rig = Rig()
    tr = rig.tracker
    for bad in ([1, 2, 3], "x", np.eye(3), np.full((4, 4), np.inf), None):
        r = tr.set_target(bad, 0.0)
        assert not r.ok and r.reason
    skew = np.eye(4)
    skew[0, 1] = 0.5
    assert not tr.set_target(skew, 0.0).ok
    assert not tr.set_target(to_mm(ready_tip_pose()), -10.0, now=0.0).ok  # captured 10 s ago


def test_units_boundary():
    assert mm_to_m(1500.0) == 1.5 and m_to_mm(0.25) == 250.0
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    assert np.allclose(transform_mm_to_m(transform_m_to_mm(T)), T)
    assert transform_m_to_mm(T)[2, 3] == 3000.0
    rig = Rig()
    rig.tracker.connect()
    s = rig.tracker.step()
    assert np.allclose(s.T_base_tool0_mm[:3, 3], m_to_mm(kin.fk(kin.Q_READY)[:3, 3]))


def test_realtime_thread_runs_and_stops():
    tr = Tracker(rate_hz=250.0)  # simulated arm on the real clock
    assert tr.connect().ok and tr.arm().ok
    T = ready_tip_pose()
    T[:3, 3] += [0.01, 0, 0]
    tr.set_target(to_mm(T), time.monotonic())
    assert tr.start_tracking().ok
    tr.start()
    t_end = time.monotonic() + 1.0
    while time.monotonic() < t_end:
        tr.set_target(to_mm(T), time.monotonic())
        time.sleep(0.02)
    snap = tr.snapshot()
    tr.stop()
    assert snap.state == "tracking"
    assert snap.tip_error_mm < 5.0  # moved most of the 10 mm in 1 s on a loaded machine
    assert tr.state.value == "armed"


def test_disconnect_disarms():
    rig = Rig()
    T = ready_tip_pose()
    rig.start(T)
    rig.run(0.1, T)
    rig.tracker.disconnect()
    assert rig.tracker.state.value == "disarmed"
    assert not rig.arm.is_connected()
