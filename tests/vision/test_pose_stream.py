"""Pose stream against the simulator's truth: accuracy, occlusion alerts, gates, camera faults."""

import threading
import time

import numpy as np

from monotracker.geometry import apply_transform
from monotracker.sim.camera_sim import Occluder, SceneEvents, SimulatedCamera, _finger
from monotracker.sim.phantom import default_phantom
from monotracker.sim.trajectories import make_trajectory
from monotracker.vision.pose_stream import NEWLY_LOST, OCCLUDED, SEEN, PoseStream, PoseTracker

PH = default_phantom()


def _tracker(cam):
    return PoseTracker(PH.fiducial_centres_lps, cam.camera, radius_mm=PH.fiducial_radius_mm,
                       target_ct=PH.sample_target_lps)


def _target_error(T, T_true):
    t = PH.sample_target_lps
    return float(np.linalg.norm(apply_transform(T, t) - apply_transform(T_true, t)))


def test_tracks_a_moving_head_to_submillimetre():
    cam = SimulatedCamera(trajectory=make_trajectory("mixed"), seed=3, start_index=330, max_frames=345)
    tr = _tracker(cam)
    ests = [tr.process(f) for f in cam]
    assert len(ests) == 15
    for e in ests:
        assert e.ok, e.reason
        assert e.status == [SEEN] * 9 and not e.alerts
        assert _target_error(e.T_cam_ct, e.truth.T_cam_ct) < 0.5
        assert 0 < e.predicted_tre_mm < 3 and e.fre_mm < 0.5 and np.nanmax(e.residuals_px) < 0.5
    assert all(e.used_prior for e in ests[1:])  # the previous pose is the prior


def test_occlusion_alert_in_the_same_frame():
    cam0 = SimulatedCamera(seed=0)
    px = cam0.rest_projection()
    k = 6
    # a hand arrives at t = 0.2 s (frame 6) and covers fiducial k completely
    oc = Occluder(0.2, 10.0, _finger(60, 900, np.pi), px[k] - [300, 0], px[k] + [20, 0], sweep_s=0.0)
    cam = SimulatedCamera(events=SceneEvents(occluders=[oc]), seed=0, max_frames=9)
    tr = _tracker(cam)
    ests = [tr.process(f) for f in cam]
    first = next(i for i, e in enumerate(ests) if not e.truth.visible[k])
    assert first == 6
    assert all(e.status[k] == SEEN and not e.alerts for e in ests[:first])
    e = ests[first]
    assert e.status[k] == NEWLY_LOST and e.newly_lost == [k]
    assert any(f"fiducial {k} lost" in a for a in e.alerts)
    assert e.ok  # 8 balls still give a valid pose
    assert ests[first + 1].status[k] == OCCLUDED and not ests[first + 1].alerts


def test_too_few_fiducials_invalidates_the_pose():
    cam0 = SimulatedCamera(seed=0)
    px = cam0.rest_projection()
    # a flat instrument covering all but 3 balls
    keep = np.argsort(px[:, 0])[-3:]
    edge = px[keep, 0].min() - 12
    poly = np.array([[0, -1000], [0, 1000], [-2000, 1000], [-2000, -1000]], float)
    oc = Occluder(0.1, 10.0, poly, np.array([edge, 360.0]), np.array([edge, 360.0]), sweep_s=0.0)
    cam = SimulatedCamera(events=SceneEvents(occluders=[oc]), seed=0, max_frames=6)
    tr = _tracker(cam)
    ests = [tr.process(f) for f in cam]
    assert ests[0].ok and not ests[-1].ok
    assert "need 4" in ests[-1].reason and ests[-1].T_cam_ct is None
    bad = next(e for e in ests if not e.ok)
    assert any("no valid pose" in a for a in bad.alerts) and len(bad.newly_lost) == 6


def _collect(stream, until, timeout=5.0):
    got = []
    done = threading.Event()

    def cb(e):
        got.append(e)
        if until(e):
            done.set()

    stream.subscribe(cb)
    stream.start()
    done.wait(timeout)
    stream.stop()
    return got


def test_stream_thread_publishes_and_reports_unplugged_camera():
    # 20 frames at 30 fps: a loaded machine skips frames (the camera hands out the newest one)
    cam = SimulatedCamera(realtime=True, disconnect_at_frame=20, seed=1)
    stream = PoseStream(cam)
    got = _collect(stream, lambda e: e.camera == "disconnected")
    assert stream.latest() is got[-1]
    assert sum(e.ok for e in got) >= 3
    assert got[-1].code == "camera_disconnected"
    assert got[-1].camera == "disconnected" and not got[-1].ok and "disconnected" in got[-1].reason
    assert all(0 <= e.latency_s < 0.5 for e in got)
    assert threading.current_thread() is threading.main_thread()


def test_frozen_camera_reported_within_100_ms():
    cam = SimulatedCamera(realtime=True, freeze_at_frame=8, seed=1)
    stream = PoseStream(cam)
    t_freeze = {}

    def until(e):
        if e.camera == "ok" and e.frame_index <= 7:
            t_freeze["index"] = e.frame_index
        return e.camera == "frozen"

    got = _collect(stream, until)
    bad = got[-1]
    assert bad.camera == "frozen" and not bad.ok and "frozen" in bad.reason and bad.code == "camera_freeze"
    # frame 7 is the last new image; frames 8 and 9 repeat it; reported on frame 9. A loaded
    # machine may skip frames (the camera hands out the newest one), so frame 7's capture time is
    # taken from the camera's own clock rather than from a published estimate of it.
    assert "index" in t_freeze
    t7 = cam._t0 + 7 / cam.fps
    # frame 7 and the first repeat are still processed; on a loaded machine that takes a while
    busy = sum(e.detect_s + e.register_s for e in got if e.camera == "ok" and e.frame_index >= 7)
    assert bad.t_published - t7 < 0.1 + 0.02 + busy


def test_stalled_camera_reported_within_100_ms():
    cam = SimulatedCamera(realtime=True, stall_at_frame=8, seed=1)
    stream = PoseStream(cam)
    got = _collect(stream, lambda e: e.camera == "stalled")
    bad = got[-1]
    last_ok = [e for e in got if e.camera == "ok"][-1]
    assert bad.camera == "stalled" and not bad.ok
    # the read of frame 8 starts ~33 ms after frame 7's capture (or when frame 7 is processed, on a
    # loaded machine); the stall is flagged 0.1 s later
    busy = last_ok.detect_s + last_ok.register_s
    assert bad.t_published - last_ok.t_capture < max(0.033, busy) + 0.1 + 0.05


def test_residual_gate_invalidates_the_pose():
    from monotracker.vision.pose_stream import TrackerConfig

    cam = SimulatedCamera(seed=0, max_frames=2)
    tr = PoseTracker(PH.fiducial_centres_lps, cam.camera, radius_mm=4.0,
                     config=TrackerConfig(max_rms_px=1e-4))
    e = tr.process(cam.read())
    assert not e.ok and "over the" in e.reason and e.T_cam_ct is None
    assert e.status == [SEEN] * 9          # the balls were matched; the fit is just not trusted
    assert any("no valid pose" in a for a in e.alerts)

