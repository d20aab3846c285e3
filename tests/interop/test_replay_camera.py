"""A recording is a camera: ``--camera replay:DIR`` feeds the recorded frames through the live
pipeline (real clock, vision's PoseStream) and yields the recorded poses again."""

import json
import shutil
import threading
import time

import numpy as np
import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.errors import InputError
from monotracker.geometry import apply_transform
from monotracker.sim.phantom import default_phantom


@pytest.fixture(scope="module")
def image_recording(planned_home, tmp_path_factory):
    """A 1 s recording of the rendered twin (made once per module: the tests that change it
    change a copy)."""
    home = tmp_path_factory.mktemp("rec-home")
    shutil.copy(planned_home / "plan.json", home / "plan.json")
    s = Session(SessionConfig(home=home, camera="sim", clock="sim"))
    rec = tmp_path_factory.mktemp("image-recording") / "rec"
    try:
        assert s.start_recording(rec).ok
        assert s.start_camera().ok
        s.advance(1.0)
        assert s.stop_recording().ok
    finally:
        s.shutdown()
    return rec


def test_replay_camera_reproduces_the_recorded_poses(image_recording, planned_home, tmp_path):
    from monotracker.engine.rigs.factory import build_camera_rig

    home = tmp_path / "home2"
    home.mkdir()
    shutil.copy(planned_home / "plan.json", home / "plan.json")
    recorded = [json.loads(line) for line in (image_recording / "poses.jsonl").read_text().splitlines()]
    assert len(recorded) >= 20
    estimates = []  # every estimate of the live pipeline (vision's PoseStream), in order
    ended = threading.Event()

    def on_estimate(est):
        if est.camera == "ok":
            estimates.append(est)
        elif est.camera == "ended":  # a "stalled" notice can also come on a loaded machine
            ended.set()

    def factory(source, calibration_path, plan, cfg, session):
        rig = build_camera_rig(source, calibration_path, plan, cfg, session)
        rig.stream.subscribe(on_estimate)
        return rig

    seen = []  # what reached the engine loop (it polls the newest; it may skip some when starved)
    s = Session(SessionConfig(home=home, camera=f"replay:{image_recording}", clock="real"), camera_factory=factory)
    try:
        s.add_pose_listener(lambda smp, trusted, now: seen.append(smp))
        s.start()
        assert s.start_camera().ok, s.snapshot().camera.error
        deadline = time.monotonic() + 240  # loaded machine: wait on state, generously
        while time.monotonic() < deadline and not ended.is_set():
            time.sleep(0.1)
        assert ended.is_set(), "the recording never reached its end"
        snap = s.snapshot()
        cal = json.loads((image_recording / "calibration.json").read_text())  # the recording's own calibration
        assert np.array_equal(snap.camera.K, np.array(cal["camera_matrix"]))
    finally:
        s.shutdown()
    target = default_phantom().sample_target_lps
    assert [e.frame_index for e in estimates] == list(range(len(recorded)))  # every frame, in order
    compared = 0
    for est, rec in zip(estimates, recorded):  # replay frame i (from 0) is recorded row i
        assert est.ok == rec["ok"]
        if rec["ok"]:
            d = apply_transform(np.asarray(est.T_cam_ct), target) - apply_transform(np.asarray(rec["T_cam_ct"]), target)
            assert np.linalg.norm(d) <= 1e-3
            compared += 1
    assert compared >= 0.8 * len(recorded)
    # the engine loop handled these same poses
    by_index = {e.frame_index: e for e in estimates}
    live = [smp for smp in seen if getattr(smp.raw, "camera", "ok") == "ok"]
    assert live and all(np.array_equal(smp.T_cam_ct, by_index[smp.frame_index].T_cam_ct) for smp in live if smp.ok)


def test_replay_camera_refuses_a_broken_recording(image_recording, fresh_home, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(image_recording, broken)
    (broken / "frames.jsonl").write_text("")
    s = Session(SessionConfig(home=fresh_home, camera=f"replay:{broken}", clock="real"))
    try:
        r = s.start_camera()
        assert not r.ok and "incomplete" in r.message
    finally:
        s.shutdown()


def test_config_accepts_replay_and_rejects_nonsense(tmp_path):
    SessionConfig(home=tmp_path, camera="replay:/x").validate()
    with pytest.raises(InputError, match="replay:DIR"):
        SessionConfig(home=tmp_path, camera="tape:/x").validate()
