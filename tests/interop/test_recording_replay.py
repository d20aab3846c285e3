"""Session recording and replay: a recording re-runs to the same poses, and a damaged one is refused.

The done criterion (issue 16): a 4 s headless demo recording on the rendered twin replays with
``max_pose_diff_mm <= 1e-3`` over >= 60 frames. The comparison itself is checked to be able to
fail: a recorded pose moved by a known 0.01 mm is reported as a 0.01 mm difference."""

import json
import shutil

import numpy as np
import pytest

from monotracker.cli import main
from monotracker.engine import Session, SessionConfig
from monotracker.errors import InputError
from monotracker.geometry import apply_transform
from monotracker.interop.replay import replay_recording
from monotracker.sim.phantom import default_phantom


def _last_json_line(text: str) -> dict:
    return json.loads(text.strip().splitlines()[-1])


# Runs 2-wide with the rest (issue 35): the demo's simulated clock counts the measured CPU time of
# each frame, not wall time, and the recording holds every estimate (the replay fix), so beside 4
# CPU hogs the 4 s demo still records 123 frames (>= 60 asserted) and replays to 0 mm (2 runs).
def test_headless_demo_recording_replays_exactly(fresh_home, tmp_path, capsys):
    rec = tmp_path / "rec"
    # the command line of the done criterion, in-process
    assert main(["demo", "--headless", "--seconds", "4", "--record", str(rec), "--home", str(fresh_home), "--json"]) == 0
    r = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert r["recording"]["ok"], r["recording"]
    manifest = json.loads((rec / "manifest.json").read_text())
    assert manifest["complete"] and manifest["frames"] >= 60
    for name in ("plan.json", "calibration.json", "frames.jsonl", "detections.jsonl", "poses.jsonl",
                 "robot.jsonl", "targets.jsonl", "events.jsonl", "alerts.jsonl"):
        assert (rec / name).is_file(), name
    # the recorded poses are the session's real poses: within 1 mm of the simulator's truth
    target = default_phantom().sample_target_lps
    poses = [json.loads(line) for line in (rec / "poses.jsonl").read_text().splitlines()]
    errs = [np.linalg.norm(apply_transform(np.array(p["T_cam_ct"]), target)
                           - apply_transform(np.array(p["truth_T_cam_ct"]), target)) for p in poses if p["ok"]]
    assert len(errs) >= 60 and max(errs) < 1.0

    # replay through the CLI: the last line is the JSON verdict
    code = main(["replay", str(rec), "--json"])
    out = _last_json_line(capsys.readouterr().out)
    assert code == 0, out
    assert out["frames"] >= 60 and out["max_pose_diff_mm"] <= 1e-3

    # a corrupted frame is refused with one line naming it (not replayed into a different pose)
    png = sorted((rec / "frames").glob("*.png"))[10]
    data = bytearray(png.read_bytes())
    data[len(data) // 2] ^= 0xFF
    png.write_bytes(bytes(data))
    with pytest.raises(InputError, match=f"{png.name}.*corrupt"):
        replay_recording(rec)
    assert main(["replay", str(rec)]) == 2


@pytest.fixture
def points_recording(fresh_home, tmp_path):
    """A 2 s recording of the point-level twin (no images: cheap), from camera start."""
    s = Session(SessionConfig(home=fresh_home, camera="sim-points", clock="sim"))
    rec = tmp_path / "points"
    try:
        assert s.start_recording(rec).ok
        assert s.start_camera().ok
        s.advance(2.0)
        snap = s.snapshot()
        assert snap.recording.running and snap.recording.frames >= 50 and snap.recording.path == str(rec)
        assert s.stop_recording().ok
        assert not s.snapshot().recording.running
    finally:
        s.shutdown()
    return rec


def test_points_recording_replays_and_detects_a_moved_pose(points_recording, tmp_path):
    r = replay_recording(points_recording)
    assert r.ok and r.frames >= 50 and r.max_pose_diff_mm <= 1e-9, r
    # move one recorded pose by 0.01 mm: replay must report that difference, not hide it
    moved = tmp_path / "moved"
    shutil.copytree(points_recording, moved)
    lines = (moved / "poses.jsonl").read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if json.loads(line)["ok"] and i > 10)
    row = json.loads(lines[k])
    row["T_cam_ct"][0][3] += 0.01
    lines[k] = json.dumps(row)
    (moved / "poses.jsonl").write_text("\n".join(lines) + "\n")
    r2 = replay_recording(moved)
    assert not r2.ok and r2.max_pose_diff_mm == pytest.approx(0.01, rel=1e-6)


def test_incomplete_or_corrupt_recordings_are_refused(points_recording, tmp_path, capsys):
    def copy(name):
        d = tmp_path / name
        shutil.copytree(points_recording, d)
        return d

    never_closed = copy("open")
    m = json.loads((never_closed / "manifest.json").read_text())
    m["complete"] = False
    (never_closed / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(InputError, match="incomplete: it was never closed"):
        replay_recording(never_closed)

    truncated = copy("truncated")
    text = (truncated / "frames.jsonl").read_text()
    (truncated / "frames.jsonl").write_text(text[: len(text) - 40])
    with pytest.raises(InputError, match="frames.jsonl line .* not valid JSON"):
        replay_recording(truncated)

    missing = copy("missing")
    (missing / "poses.jsonl").unlink()
    with pytest.raises(InputError, match="poses.jsonl is missing"):
        replay_recording(missing)

    assert main(["replay", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: recording folder not found") and len(err.strip().splitlines()) == 1

    # a point-level recording is not a camera
    from monotracker.vision.replay_source import ReplaySource

    with pytest.raises(InputError, match="holds detected points"):
        ReplaySource(points_recording)


def test_recording_refuses_a_folder_that_holds_one(points_recording, fresh_home):
    s = Session(SessionConfig(home=fresh_home, camera="sim-points", clock="sim"))
    try:
        r = s.start_recording(points_recording)
        assert not r.ok and "already holds a recording" in r.message
        assert s.snapshot().recording is None
    finally:
        s.shutdown()


def test_a_recording_holds_every_frame_the_tracker_estimated_through_a_stale_spell(fresh_home, tmp_path):
    """The silent-wrong behind the demo replay that differed by 0.0068 mm under load: a slow
    estimate (on the simulated clock its cost is its thread CPU time, so a loaded machine makes
    one) made a pose stale; the fresh poses of the resume dwell that followed were estimated (the
    tracker's prior and noise estimate moved on) but never reached the recording, so the replay
    ran a different history. Here one estimate burns a fixed 0.25 s of its own CPU time (machine
    speed and load do not matter): every estimated frame must be recorded, and the replay must
    reproduce every pose exactly. Independent truth: the frames the rig estimated, counted around
    its ``estimate``."""
    import time

    from monotracker.engine.alarms import FRESHNESS_CODES
    from monotracker.engine.rigs.factory import build_camera_rig

    estimated = []
    slow_at = 30   # the estimate that burns 0.25 s (> max_pose_age_s 0.15 s: that pose is stale)

    def factory(source, calibration_path, plan, cfg, session):
        rig = build_camera_rig(source, calibration_path, plan, cfg, session)
        estimate = rig.estimate

        def counted(frame):
            estimated.append((frame.index, frame.t_capture))
            if len(estimated) == slow_at:
                c0 = time.thread_time()
                while time.thread_time() - c0 < 0.25:
                    pass
            return estimate(frame)

        rig.estimate = counted
        return rig

    s = Session(SessionConfig(home=fresh_home, camera="sim-points", clock="sim"), camera_factory=factory)
    rec = tmp_path / "stale"
    try:
        holds = []   # (session s, why the engine holds) at every control tick
        s.add_tick_listener(lambda t: holds.append((t, s._loop.holding_state()[0])))
        assert s.start_recording(rec).ok and s.start_camera().ok
        s.advance(2.0)
        assert s.stop_recording().ok
    finally:
        s.shutdown()
    assert len(estimated) > slow_at + 20
    # the slow estimate made the engine hold for freshness (the spell this test is about)
    t_slow = estimated[slow_at - 1][1]
    assert any(code in FRESHNESS_CODES for t, code in holds if t > t_slow), sorted({c for _, c in holds} - {None})
    rows = [json.loads(line) for line in (rec / "frames.jsonl").read_text().splitlines()]
    # every estimate is in the recording, in order, but the last ones still in flight (transport
    # + compute) when the recording stopped: at most 2 at 30 fps with the 30 ms transport delay
    recorded = [(r["index"], r["t_capture"]) for r in rows]
    assert recorded == estimated[: len(recorded)] and len(recorded) >= len(estimated) - 2, \
        sorted(set(estimated) - set(recorded))
    r = replay_recording(rec)
    assert r.ok and r.ok_mismatches == 0 and r.max_pose_diff_mm <= 1e-9, r
