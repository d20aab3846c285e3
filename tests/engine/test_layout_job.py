"""The layout job (issue 31): ``Session.plan_layout`` plans off the UI threads with progress and
cancel, refuses while the robot is armed, stops when it gets armed, and puts the result in
``snap.layout``.

Truths: the analytic head phantom the sample CT was made from (its skin ellipsoid, its nine
balls, the sample target), the camera model's own projection, hand-made transforms for the
placement offset, and the order of events a recording double of the robot state forces (no
timing)."""

from __future__ import annotations

import re
import threading
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from monotracker.engine import Session, SessionConfig
from monotracker.engine.access import NOT_IN_CONTROL
from monotracker.engine.layout_job import LayoutJob, placement_offset
from monotracker.engine.plan.model import Plan, PlanFiducial
from monotracker.engine.snapshot import HeadMesh
from monotracker.sim.phantom import default_phantom
from monotracker.vision.camera_model import default_camera

from .conftest import plan_sample
from .doubles import FollowerRobotRig, TruthCameraRig

PH = default_phantom()


# ---------------------------------------------------------------- the session on the sample CT
@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    """The sample CT, its detected balls confirmed, the sample plan; a quick 9-ball layout."""
    s = Session(SessionConfig(home=tmp_path_factory.mktemp("layout"), clock="sim"))
    assert s.load_sample_ct().ok
    job = s.wait_for_job(300)
    assert job.error is None, job.error
    for f in s.snapshot().fiducials:
        s.set_fiducial_status(f.id, "confirmed")
    assert s.confirm_fiducials().ok and s.use_sample_plan().ok
    seen = []
    unsubscribe = s.subscribe(lambda ev: seen.append(ev.code))
    r = s.plan_layout(9, quick=True)
    assert r.ok, r.message
    job = s.wait_for_layout(600)
    unsubscribe()
    yield s, job, seen
    s.shutdown()


def test_the_layout_is_in_the_snapshot_and_keeps_to_the_head(planned):
    s, job, seen = planned
    assert job.done and job.error is None and job.progress == 1.0, job
    assert "layout_started" in seen and "layout_planned" in seen
    lay = s.snapshot().layout
    assert lay.ready and not lay.stale and lay.job is job
    B = np.asarray(lay.balls_lps_mm)
    assert B.shape == (9, 3)
    # every suggested ball rests on the phantom's skin: its centre one radius out of the ellipsoid
    r = PH.fiducial_radius_mm
    q = np.linalg.norm((B - PH.centre_lps) / (PH.skin_semi_axes_mm + r), axis=1)
    assert np.all(np.abs(q - 1.0) < 0.03), q
    # a kept ball is one of the plan's fiducials, where the CT has it
    fids = {f.id: np.asarray(f.centre_lps_mm) for f in s.snapshot().fiducials}
    for b, fid in zip(B, lay.from_fiducial):
        if fid >= 0:
            assert np.linalg.norm(b - fids[fid]) < 1e-6
    # the notes name the plan's fiducials by their ids (the CT's balls on the head's outline)
    named = {int(m) for n in lay.notes if n.startswith("CT fiducial") for m in re.findall(r"#(\d+)", n)}
    assert named <= set(fids), (named, set(fids))
    # the planned camera sees every suggested ball inside its image, in front of it
    T = np.asarray(lay.T_ct_cam)
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    cam = default_camera()
    T_cam_ct = np.linalg.inv(T)
    Xc = B @ T_cam_ct[:3, :3].T + T_cam_ct[:3, 3]
    assert np.all(Xc[:, 2] > 300.0)
    uv = Xc[:, :2] / Xc[:, 2:] * [cam.K[0, 0], cam.K[1, 1]] + cam.K[:2, 2]
    assert np.all((uv > 0) & (uv < cam.image_size)), uv
    assert lay.K is not None and lay.image_size == (1280, 720)
    # what to expect: the suggestion beats the CT's own balls from the same camera, and a hidden ball costs
    sug, cur = lay.suggestion, lay.current
    assert sug.balls == 9 and sug.all_seen is not None and sug.worst_hidden is not None
    assert sug.worst_hidden.p95_mm >= sug.all_seen.p95_mm > sug.all_seen.mean_mm > 0
    assert cur is not None and cur.balls == 9
    assert cur.all_seen is None or sug.worst_hidden.rms_mm < (cur.worst_hidden or cur.all_seen).rms_mm
    # 95 % trusted with one ball hidden, or the count it would take
    assert sug.worst_hidden.trusted >= lay.min_trusted or lay.balls_needed is not None
    # the map: one value per candidate, the suggestion's own value among the best
    assert len(lay.error_map_mm) == len(lay.candidates_lps_mm) > 50
    assert np.nanmin(lay.error_map_mm) <= sug.worst_hidden.rms_mm + 1e-9


def test_a_changed_target_makes_the_layout_stale(planned):
    s, _, _ = planned
    t0 = np.asarray(s.snapshot().plan.target_lps_mm).copy()
    assert s.set_target(t0 + [0.0, 5.0, 0.0]).ok
    assert s.snapshot().layout.stale
    assert s.set_target(t0).ok
    assert not s.snapshot().layout.stale


# ---------------------------------------------------------------- refusals in the session
def test_refused_without_a_ct_and_while_armed(make_session):
    cam, rob = TruthCameraRig("still"), FollowerRobotRig()
    s = make_session(clock="sim", camera_factory=lambda *a: cam, robot_factory=lambda *a: rob)
    r = s.plan_layout(9)
    assert not r.ok and r.message.startswith("load a CT first")
    tab = s.for_client("tab-b")  # a browser tab not in control: a command, refused; waiting is a read
    r = tab.plan_layout(9)
    assert not r.ok and r.message == NOT_IN_CONTROL
    assert tab.wait_for_layout(0) is None and not tab.cancel_layout().ok
    plan_sample(s)
    assert s.start_camera().ok
    s.advance(0.3)
    assert s.arm("1234").ok
    r = s.plan_layout(9)
    assert not r.ok and "disarm" in r.message and "armed" in r.message
    assert s.snapshot().layout is None
    for bad, why in ((3, "ball count must be 4-16"), (17, "ball count must be 4-16"), (6.5, "whole number")):
        r = s.plan_layout(bad)
        assert not r.ok and why in r.message, r.message


# ---------------------------------------------------------------- the job on its own (analytic head)
class _Bus:
    def __init__(self):
        self.codes = []

    def event(self, code, *a, **k):
        self.codes.append(code)

    def alert(self, level, code, *a, **k):
        self.codes.append(code)


def _job(robot_state, **kw):
    """A LayoutJob on the phantom's skin ellipsoid with its nine balls and the sample plan."""
    m = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    mesh = HeadMesh(np.asarray(m.vertices) * PH.skin_semi_axes_mm + PH.centre_lps, np.asarray(m.faces))
    plan = Plan(fiducials=[PlanFiducial(10 + i, c, PH.fiducial_radius_mm, 1.0, "confirmed")
                           for i, c in enumerate(PH.fiducial_centres_lps)],
                fiducials_locked=True, entry_lps_mm=PH.sample_entry_lps, target_lps_mm=PH.sample_target_lps)
    loaded = SimpleNamespace(head_mesh=mesh, summary=SimpleNamespace(path="phantom"))
    bus = _Bus()
    job = LayoutJob(lock=threading.RLock(), editor=SimpleNamespace(plan=plan), ct=lambda: loaded,
                    ct_job=lambda: None, robot_state=robot_state, camera_rig=lambda: None,
                    config=SessionConfig(), events=bus, **kw)
    return job, bus, plan


@pytest.fixture(scope="module")
def replanned():
    """One LayoutJob on the analytic head with a finished quick 6-ball plan, for the tests that
    stop a second plan and check that this first one stays (planned once: ~8 s). The test steers
    it through ``ctl``: ``on_read()`` is called at each read of the robot state (always
    "disarmed"), ``step`` is how much later (s) each read of the job's clock is. The job's time
    limit is 300 s; with ``step`` 0 no time passes."""
    ctl = {"on_read": None, "step": 0.0, "now": 0.0}

    def robot_state():
        if ctl["on_read"] is not None:
            ctl["on_read"]()
        return "disarmed"

    def clock():
        ctl["now"] += ctl["step"]
        return ctl["now"]

    job, bus, _ = _job(robot_state, time_limit_s=300.0, clock=clock)
    assert job.start(6, quick=True).ok
    first = job.wait(300)
    assert first.done and first.error is None, first  # no time passes: the plan completes
    before = job.summary()
    assert before.ready and before.balls_lps_mm.shape == (6, 3)
    assert bus.codes.count("layout_planned") == 1
    return job, bus, before, ctl


@pytest.fixture
def replan(replanned):
    """:func:`replanned` with its steering put back after the test."""
    yield replanned
    ctl = replanned[3]
    ctl.update(on_read=None, step=0.0)


def test_the_notes_name_the_plans_fiducials_by_their_ids(replanned):
    """The plan's fiducials are numbered 10-18 here: the note on the balls the planned camera sees
    on the head's outline names those ids, never the planner's indices 0-8."""
    _, _, before, _ = replanned
    named = {int(m) for n in before.notes if n.startswith("CT fiducial") for m in re.findall(r"#(\d+)", n)}
    assert named and named <= set(range(10, 19)), before.notes


def test_cancel_keeps_the_previous_layout(replan):
    job, bus, before, ctl = replan
    assert job.wait(300).done          # nothing runs before the second plan
    reads = [0]

    def on_read():
        reads[0] += 1
        if reads[0] == 3:               # three progress steps into the second plan
            assert job.cancel().ok      # the operator's click, mid-run

    ctl["on_read"] = on_read
    n0 = len(bus.codes)
    assert job.start(7, quick=True).ok
    end = job.wait(300)
    assert end.done and end.error == "cancelled by the operator" and end.message == "layout planning stopped"
    after = job.summary()
    assert after.job is end and after.balls_lps_mm is before.balls_lps_mm  # the first plan stays
    assert not job.cancel().ok  # nothing runs now
    assert "layout_planned" not in bus.codes[n0:] and "layout_stopped" in bus.codes[n0:]


def test_arming_while_planning_stops_the_plan():
    states = iter(["disarmed", "disarmed", "disarmed"])  # start, then two progress steps; then armed

    def robot_state():
        return next(states, "armed")

    job, bus, _ = _job(robot_state)
    assert job.start(6, quick=True).ok
    end = job.wait(300)
    assert end.done and end.error.startswith("the robot was armed"), end
    assert not job.summary().ready
    assert "layout_planned" not in bus.codes


def test_a_plan_past_its_time_limit_stops_with_a_reason_and_keeps_the_previous_layout(replan):
    job, bus, before, ctl = replan     # its first plan completed with no time passing
    assert job.time_limit_s == 300.0
    ctl["step"] = 60.0                 # each read of the clock is one minute later from now on
    n0 = len(bus.codes)
    assert job.start(7, quick=True).ok
    end = job.wait(300)
    assert end.done and end.message == "layout planning stopped", end
    assert end.error.startswith("planning took longer than its 300 s limit"), end.error
    assert job.summary().balls_lps_mm is before.balls_lps_mm  # the first plan stays
    assert "layout_planned" not in bus.codes[n0:] and "layout_stopped" in bus.codes[n0:]


def test_a_plan_the_planner_refuses_is_one_line():
    job, _, plan = _job(lambda: "disarmed")
    plan.target_lps_mm = PH.centre_lps + [0.0, 0.0, 500.0]  # far outside the head
    assert job.start(6, quick=True).ok
    end = job.wait(300)
    assert end.done and end.error == "the target lies outside the head surface's extent; check its LPS coordinates"


def test_placement_offset_against_a_hand_made_move():
    from scipy.spatial.transform import Rotation

    T_ct_cam = np.eye(4)
    T_ct_cam[:3, :3] = Rotation.from_euler("xyz", [20, -35, 5], degrees=True).as_matrix()
    T_ct_cam[:3, 3] = [100.0, -250.0, 300.0]
    moved = T_ct_cam.copy()
    # 10 deg about the camera's own x axis (tilts the viewing axis by 10 deg), 30 mm along its y
    moved[:3, :3] = T_ct_cam[:3, :3] @ Rotation.from_euler("x", 10, degrees=True).as_matrix()
    moved[:3, 3] = T_ct_cam[:3, 3] + 30.0 * T_ct_cam[:3, 1]
    mm, deg = placement_offset(T_ct_cam, np.linalg.inv(moved))
    assert mm == pytest.approx(30.0, abs=1e-9) and deg == pytest.approx(10.0, abs=1e-9)
    # a roll about the viewing axis does not change where it looks
    rolled = T_ct_cam.copy()
    rolled[:3, :3] = T_ct_cam[:3, :3] @ Rotation.from_euler("z", 40, degrees=True).as_matrix()
    assert placement_offset(T_ct_cam, np.linalg.inv(rolled)) == pytest.approx((0.0, 0.0), abs=1e-6)


def test_the_camera_planned_with_is_the_plans_calibration_else_the_rigs_else_the_simulated():
    from monotracker.engine.layout_job import planning_camera

    K = np.array([[1500.0, 0, 960], [0, 1500.0, 540], [0, 0, 1]])
    rig = SimpleNamespace(K=K * [[0.5], [0.5], [1]], dist=None, image_size=(960, 540))
    calibrated = Plan(K=K, dist=np.zeros(5), image_size=(1920, 1080))
    assert np.allclose(planning_camera(calibrated, rig).K, K)
    got = planning_camera(Plan(), rig)
    assert np.allclose(got.K, rig.K) and got.image_size == (960, 540)
    sim = default_camera()
    assert np.allclose(planning_camera(Plan(), None).K, sim.K)
    broken = Plan(K=np.zeros((3, 3)), image_size=(1920, 1080))  # refused by CameraModel: skipped
    assert np.allclose(planning_camera(broken, None).K, sim.K)
