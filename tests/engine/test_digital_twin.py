"""End to end on the digital twin: the sample CT through the real CT detector, the real
registration on simulated camera points, the real robot Tracker (APFF + safety) on the simulated
UR10, all driven by the engine on a simulated clock. Accuracy is checked against the simulator's
truth (true head pose, true arm joint state)."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.demo.run import DemoOptions, run_demo
from monotracker.robot.targets import tip_and_axis_error

ROOT = Path(__file__).resolve().parents[2]
# waits on a state (a job done, a child exited), never a guess at speed: generous enough for a
# machine shared by many loaded processes (the CT job took over 120 s at load average 30)
JOB_WAIT_S = 900
CHILD_WAIT_S = 900
#: What the simulated clock charges each estimate in the tests of the loop's logic (s;
#: SessionConfig.compute_charge_s): about the demo's p95 pipeline time on a quiet 2-core machine
#: (11.8 ms measured), fixed so that faults, holds and stops give the same figures beside any load
#: and these tests run 2-wide with the suite. The tests that drive the real clock or report the
#: measured pipeline keep @pytest.mark.serial (tests/conftest.py).
LOGIC_CHARGE_S = 0.015
LOGIC = {"compute_charge_s": LOGIC_CHARGE_S}


@pytest.fixture(scope="module")
def planned_home(tmp_path_factory):
    """A session folder holding a plan made on the sample CT (CT loaded once for the module)."""
    home = tmp_path_factory.mktemp("planned")
    s = Session(SessionConfig(home=home, clock="sim"))
    assert s.load_sample_ct().ok
    job = s.wait_for_job(JOB_WAIT_S)
    assert job.error is None, job.error
    for f in s.snapshot().fiducials:
        s.set_fiducial_status(f.id, "confirmed")
    assert s.confirm_fiducials().ok and s.use_sample_plan().ok
    s.shutdown()
    return home


def _home_with_plan(planned_home, tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    shutil.copy(planned_home / "plan.json", home / "plan.json")
    return home


def test_ct_fiducials_match_the_phantom(planned_home):
    from monotracker.engine.plan import load_plan
    from monotracker.sim.phantom import default_phantom

    plan = load_plan(planned_home / "plan.json")
    truth = default_phantom().fiducial_centres_lps
    got = plan.fiducial_centres()
    assert len(got) == 9
    d = np.linalg.norm(got[:, None] - truth[None], axis=2).min(axis=1)
    assert d.max() < 0.3


def test_tracks_the_breathing_head(planned_home, tmp_path):
    r = run_demo(DemoOptions(seconds=6.0, trajectory="breathing", home=_home_with_plan(planned_home, tmp_path),
                             config_overrides=LOGIC))
    assert r["final_state"] == "tracking"
    # A fixed compute charge per estimate (LOGIC_CHARGE_S): only a working loop is asserted here;
    # the rate achieved with the measured cost is a benchmark figure.
    assert r["frames"] >= 60 and r["fps"] >= 10.0
    assert r["registration_tre_mm"]["max"] < 2.0
    assert r["tip_error_mm"]["mean"] < 1.0 and r["tip_error_mm"]["max"] < 2.0
    assert r["axis_error_deg"]["max"] < 1.0
    assert r["tracking_fraction"] > 0.99
    assert 0 < r["latency_ms"]["mean"] < 100
    assert not [a for a in r["alerts"] if a["level"] == "alarm"]


def test_a_fixed_compute_charge_is_what_the_simulated_clock_charges(planned_home, tmp_path):
    """SessionConfig.compute_charge_s: every estimate costs exactly that (s) on the simulated clock,
    whatever the estimate really took, so a pose is never younger than the camera's 30 ms
    transport plus the charge (the default, None, charges the measured CPU time)."""
    r = run_demo(DemoOptions(seconds=2.0, trajectory="breathing", home=_home_with_plan(planned_home, tmp_path),
                             config_overrides={"compute_charge_s": 0.02}))
    pm = r["pipeline_ms"]
    assert pm["n"] > 20 and pm["p50"] == pytest.approx(20.0, abs=1e-9) and pm["p99"] == pytest.approx(20.0, abs=1e-9)
    assert r["pose_age_ms"]["mean"] >= 50.0 - 1e-6 and r["final_state"] == "tracking"


@pytest.mark.parametrize("bad", [-0.01, 11.0, "0.02", True, float("nan")])
def test_compute_charge_must_be_seconds_on_the_simulated_clock(bad):
    from monotracker.errors import InputError

    with pytest.raises(InputError, match="compute_charge_s must be a number of seconds"):
        SessionConfig(clock="sim", compute_charge_s=bad).validate()
    with pytest.raises(InputError, match="clock='sim' only"):
        SessionConfig(clock="real", compute_charge_s=0.02).validate()
    SessionConfig(clock="sim", compute_charge_s=0.0).validate()


def test_partial_occlusion_keeps_tracking_with_four_and_holds_with_three(planned_home, tmp_path):
    s = Session(SessionConfig(home=_home_with_plan(planned_home, tmp_path), clock="sim", trajectory="breathing",
                              compute_charge_s=LOGIC_CHARGE_S))
    try:
        assert s.load_ct(s.plan_copy().ct_path).ok  # arming checks the path against the plan's CT
        assert s.wait_for_job(JOB_WAIT_S).error is None
        assert s.start_camera().ok
        s.advance(0.5)
        assert s.arm("1234").ok and s.start_tracking().ok
        s.advance(3.0)
        rig = s._loop.camera.rig  # test-only: the twin's drape over some balls
        rig.occluded_ids = {0, 1, 2, 3, 4}  # 4 of 9 remain
        s.advance(1.0)
        snap = s.snapshot()
        assert snap.robot.state == "tracking" and snap.pose.trusted and snap.pose.n_visible == 4
        plan = s.plan_copy()
        tip, ang = tip_and_axis_error(s.robot_status().T_base_tip, s.truth_T_base_ct(snap.t), plan.entry_lps_mm,
                                      plan.target_lps_mm)
        assert tip < 2.0 and ang < 1.5
        lost = [a for a in snap.alerts if a.code == "fiducials_lost"]
        assert lost and "4 of 9 seen; tracking continues" in lost[-1].message
        rig.occluded_ids = {0, 1, 2, 3, 4, 5}  # 3 remain
        s.advance(0.5)
        snap = s.snapshot()
        assert snap.robot.state == "holding" and not snap.pose.trusted
        assert snap.alerts[-1].code == "occlusion"
        assert np.max(np.abs(s.robot_status().qd)) < 1e-3  # standing still
        rig.occluded_ids = set()
        s.advance(0.5)
        snap = s.snapshot()
        assert snap.robot.state == "tracking" and snap.alerts[-1].code == "resumed"
        assert "fiducials_back" in [a.code for a in snap.alerts]
        rows = s.audit_entries()
        codes = [e.code for e in rows]
        assert "occlusion" in codes and "resumed" in codes
        reg = next(e for e in rows if e.code == "registration")  # the first lock is audited with its pose
        assert reg.data["n_matched"] == 9 and np.asarray(reg.data["T_cam_ct_mm"]).shape == (4, 4)
        assert next(e for e in rows if e.code == "tracking_started").data["registration"]["fre_mm"] < 1.0
    finally:
        s.shutdown()


@pytest.mark.parametrize("fault,codes,state", [
    ("camera-freeze", ("camera_freeze",), "holding"),
    ("robot-disconnect", ("robot_disconnected",), "estopped"),
    ("occlude-all", ("occlusion",), "holding"),
    ("bad-pose", ("pose_jump",), "holding"),
])
def test_fault_stops_the_arm_raises_the_alert_and_keeps_the_plan(planned_home, tmp_path, fault, codes, state):
    from monotracker.sim.trajectories import Breathing

    # a head oscillating 4 mm at 0.5 Hz (12.6 mm/s peak); the fault hits where it moves fastest,
    # so the arm is really moving whatever the machine's load did to when tracking started (a
    # fixed offset from the start once caught the head near a turning point: 2.95 mm/s)
    fast = Breathing(amplitude_mm=4.0, period_s=2.0)
    r = run_demo(DemoOptions(seconds=4.0, trajectory=fast, fault=fault, fault_at_s=2.0, fault_at_fastest_within_s=1.0,
                             home=_home_with_plan(planned_home, tmp_path), config_overrides=LOGIC))
    fr = r["fault_report"]
    assert fr["engine_reported"] is not None and fr["engine_reported"].split("]")[1].split(":")[0].strip() in codes
    assert fr["detection_delay_s"] <= 0.15
    assert fr["standstill_at_s"] is not None
    if fault in ("camera-freeze", "robot-disconnect"):
        assert fr["tip_speed_before_fault_mm_s"] > 3.0  # it was moving: stopping is a real test
        assert fr["standstill_after_detection_s"] <= 0.1
    assert fr["state_after"] == state
    assert fr["plan_intact"]
    # the needle stopped near where it was (it follows the head until the fault is detected);
    # wrong poses never pulled it anywhere
    assert fr["arm_travel_after_fault_mm"] < 2.0


@pytest.mark.serial  # a demo subprocess reporting its measured pipeline: tests/conftest.py
def test_cli_headless_demo_json_and_bad_input(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT / "app"), MONOTRACKER_HOME=str(tmp_path))
    cmd = [sys.executable, "-m", "monotracker", "demo", "--headless", "--seconds", "2", "--trajectory", "still",
           "--json"]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, timeout=CHILD_WAIT_S)
    assert p.returncode == 0, p.stderr
    r = json.loads(p.stdout)
    assert r["frames"] > 50 and r["final_state"] == "tracking" and r["tip_error_mm"] is not None
    # the pose pipeline's figures (issue 29): per-frame cost, pose age, tracking after the lock
    assert r["detect_register_ms_median"] > 0 and r["pipeline_ms"]["p95"] >= r["pipeline_ms"]["p50"] > 0
    assert {"detect", "register", "screen", "gates"} <= set(r["stages_ms"])
    assert r["pose_age_ms"]["p95"] >= 30.0   # never younger than the camera's 30 ms transport
    assert 0.0 < r["tracking_fraction_after_lock"] <= 1.0 and r["latency_ms"]["p95"] > 0
    p = subprocess.run(cmd[:-1] + ["--seconds", "-1"], capture_output=True, text=True, env=env, cwd=ROOT,
                       timeout=CHILD_WAIT_S)
    last = p.stderr.strip().splitlines()[-1]
    assert p.returncode == 2 and "error: argument --seconds: -1 must be > 0" in last and "Traceback" not in p.stderr


@pytest.mark.serial  # the real clock: tests/conftest.py
def test_real_clock_threads_track_and_snapshots_are_safe_from_other_threads(planned_home, tmp_path):
    """clock="real": camera thread, engine thread and the robot's control thread; viser-like
    worker threads read snapshots and send commands meanwhile."""
    import threading
    import time

    s = Session(SessionConfig(home=_home_with_plan(planned_home, tmp_path), clock="real", trajectory="breathing"))
    errors = []
    child = None
    try:
        assert s.start().ok
        s.wait_for_job(JOB_WAIT_S)  # the restart reloads the CT surface in the background; let it finish
        assert s.start_camera().ok
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not (s.snapshot().pose and s.snapshot().pose.trusted):
            time.sleep(0.05)
        deadline = time.monotonic() + 10
        while not (r := s.arm("1234")).ok and time.monotonic() < deadline:
            time.sleep(0.02)  # arming needs a fresh trusted pose: retry as an operator would
        assert r.ok, r.message
        deadline = time.monotonic() + 10
        while not (r := s.start_tracking()).ok and time.monotonic() < deadline:
            time.sleep(0.02)  # on a loaded machine the pose may be momentarily stale: retry as an operator would
        assert r.ok, r.message
        err0 = s.snapshot().robot.tip_error_mm  # the arm starts 60 mm back from the entry
        stop = threading.Event()
        seen = {"n": 0, "held_stale": 0}

        def hammer():
            try:
                while not stop.is_set():
                    snap = s.snapshot()
                    assert snap.robot.state in ("tracking", "holding")
                    seen["n"] += 1
                    seen["held_stale"] += snap.robot.state == "holding" and snap.pose.stale
                    s.latest_frame()
                    assert not s.set_fiducial_status(0, "rejected").ok  # locked: refused, no exception
            except Exception as exc:  # noqa: BLE001
                errors.append(exc)

        workers = [threading.Thread(target=hammer) for _ in range(3)]
        for w in workers:
            w.start()
        time.sleep(2.5)
        stop.set()
        for w in workers:
            w.join()
        assert not errors, errors
        snap = s.snapshot()
        # no timing assertions here (the machine may be loaded): the threads ran, the arm tracked
        assert snap.robot.state in ("tracking", "holding") and snap.camera.frames > 10 and snap.camera.fps > 0
        assert "tracking_started" in [e.code for e in s.audit_entries()]
        # it moved towards the entry (how fast depends on load), unless the machine is so loaded
        # that poses mostly arrive older than max_pose_age_s: then the arm must hold, and say so
        assert snap.robot.tip_error_mm < err0 - 5.0 or seen["held_stale"] > 0.5 * seen["n"], seen
        assert snap.robot.latency_ms is not None and snap.robot.latency_ms > 0
        assert s.inject_fault("camera-freeze").ok
        time.sleep(0.5)
        snap = s.snapshot()
        assert snap.robot.state == "holding" and "camera_freeze" in [a.code for a in snap.alerts]
        # the control loop ran in its own process (SessionConfig.control_process, the default)
        assert snap.robot.control.startswith("control process pid"), snap.robot.control
        child = s._loop.robot.rig.proc.proc
        assert child.is_alive() and child.pid != os.getpid()
        assert s.estop().ok and s.snapshot().robot.state == "estopped"  # latched at once
    finally:
        s.shutdown()
    assert not [t for t in threading.enumerate() if t.name.startswith(("monotracker", "robot-tracker"))]
    assert child is not None and not child.is_alive()  # shutdown ends the control process


@pytest.mark.serial  # the real clock: tests/conftest.py
def test_restart_reloads_the_ct_for_the_views_and_keeps_the_confirmed_fiducials(planned_home, tmp_path):
    home = _home_with_plan(planned_home, tmp_path)
    (home / "plan.json").write_text((home / "plan.json").read_text())
    s = Session(SessionConfig(home=home, clock="real"))
    try:
        before = s.plan_copy().to_dict()
        s.start()
        job = s.wait_for_job(JOB_WAIT_S)
        assert job is not None and job.error is None
        snap = s.snapshot()
        assert snap.ct is not None and snap.head_mesh is not None and len(snap.head_mesh.faces) > 100
        assert snap.plan.angle_to_skin_normal_deg is not None and snap.plan.angle_to_skin_normal_deg < 60
        after = s.plan_copy().to_dict()
        assert after["fiducials"] == before["fiducials"] and after["entry_lps_mm"] == before["entry_lps_mm"]
        assert snap.robot.state == "disarmed"
    finally:
        s.shutdown()


@pytest.mark.serial  # the real clock: tests/conftest.py
def test_camera_calibration_is_saved_in_the_plan_and_events_reach_subscribers_on_their_thread(planned_home, tmp_path):
    import threading
    import time

    from monotracker.engine.plan import load_plan

    home = _home_with_plan(planned_home, tmp_path)
    s = Session(SessionConfig(home=home, clock="real"))
    got = []
    s.subscribe(lambda e: got.append((e.code, threading.current_thread().name)))
    try:
        s.start()
        s.wait_for_job(JOB_WAIT_S)
        assert s.start_camera().ok
        time.sleep(0.3)
        rig = s._loop.camera.rig
        saved = load_plan(home / "plan.json")
        assert saved.camera_source == "sim" and np.allclose(saved.K, rig.K) and saved.image_size == rig.image_size
        assert np.allclose(saved.dist, np.ravel(rig.dist))
    finally:
        s.shutdown()
    assert ("camera_calibration", "monotracker-events") in got  # delivered on the bus thread, not the caller's


@pytest.mark.serial  # the camera thread on the real clock: tests/conftest.py
def test_simulated_camera_thread_survives_a_failing_frame(planned_home):
    """An exception while capturing one frame must not kill the camera thread for good."""
    import time as _time

    from monotracker.engine.plan import load_plan
    from monotracker.engine.rigs.sim import ProjectedFiducialRig

    rig = ProjectedFiducialRig(load_plan(planned_home / "plan.json"), trajectory="still")
    real_capture, calls = rig.capture, []

    def flaky_capture(t):
        calls.append(t)
        if len(calls) == 1:
            raise RuntimeError("sensor glitch")
        return real_capture(t)

    rig.capture = flaky_capture
    rig.start()
    try:
        deadline = _time.monotonic() + 10.0
        frames = []
        while not frames and _time.monotonic() < deadline:
            _time.sleep(0.05)
            frames = rig.poll_frames()
        assert frames, "no frame after the failing one: the camera thread died"
        assert rig.last_error == "RuntimeError: sensor glitch"
    finally:
        rig.stop()


@pytest.mark.parametrize("fault,within_s", [("camera-bump", 0.25), ("camera-sag", 2.5)])
def test_a_moved_camera_stops_the_arm(planned_home, tmp_path, fault, within_s):
    """The twin camera knocked (1.5 deg + 3 mm at once) or sagging (0.1 deg/s) while tracking:
    the poses stay consistent (the registration is to the camera), only the background shows it;
    the running app's tracker watches it (SessionConfig.camera_motion_every) and the arm holds with
    camera_moved, on the simulated clock."""
    r = run_demo(DemoOptions(seconds=5.0, trajectory="breathing", fault=fault, fault_at_s=1.5,
                             home=_home_with_plan(planned_home, tmp_path), config_overrides=LOGIC))
    fr = r["fault_report"]
    assert fr["engine_reported"] is not None and "] camera_moved:" in fr["engine_reported"], r["alerts"]
    assert "the camera moved since tracking started" in fr["engine_reported"]
    assert fr["detection_delay_s"] <= within_s
    assert fr["standstill_at_s"] is not None and fr["state_after"] == "holding" and fr["plan_intact"]
    # nothing before the fault: no false alarm while the head breathed in front of the still camera
    assert not [a for a in r["alerts"] if a["code"] == "camera_moved" and a["t"] < fr["injected_at_s"]]
    assert fr["arm_travel_after_detection_mm"] < 2.0


def test_camera_motion_faults_need_the_rendered_camera(planned_home, tmp_path):
    s = Session(SessionConfig(home=_home_with_plan(planned_home, tmp_path), clock="sim", camera="sim-points"))
    try:
        assert s.start_camera().ok
        r = s.inject_fault("camera-bump")
        assert not r.ok and "use camera 'sim'" in r.message
    finally:
        s.shutdown()
