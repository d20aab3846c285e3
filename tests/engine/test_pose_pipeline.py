"""The real-clock pose pipeline's plumbing: the twin camera's render process (honest stamps, newest
frame only, no torn frames, clean shutdown) and the priority policy (``engine/pipeline_priority.py``:
real time for the robot's control process only; vision and the camera process at normal
priority, never above the web server), checked against what the OS says each thread runs at.
Behaviour only; latency figures live in benchmarks/pose_latency.py and benchmarks/stop_latency.py."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from monotracker.engine.pipeline_priority import normal_priority
from monotracker.engine.rigs.sim_camera_process import SLOTS, SimCameraProcess, _slot_layout

ROOT = Path(__file__).resolve().parents[2]
T_STATE = 120.0  # s: generous, for a loaded machine


def _camera(delay_s=0.03):
    from monotracker.sim.or_layout import default_layout

    layout = default_layout()
    motion = layout.motion("breathing", seed=1)
    kwargs = dict(trajectory=motion, fps=30.0, seed=0, T_cam_world=layout.T_cam_ct0, optics=None)
    return SimCameraProcess(kwargs, (1280, 720), 30.0, delay_s), layout, motion


def _frames(proc, n):
    got, t0 = [], time.monotonic()
    while len(got) < n:
        assert time.monotonic() - t0 < T_STATE, f"only {len(got)} frames in {T_STATE:.0f} s"
        f = proc.next_frame(0.2)
        if f is not None:
            got.append((time.monotonic(), f))
    return got


def test_camera_process_frames_are_honestly_stamped_newest_first_and_match_the_truth():
    proc, layout, motion = _camera(delay_s=0.03)
    proc.start(ready_timeout_s=T_STATE)
    try:
        assert proc.alive() and proc.pid != os.getpid()
        got = _frames(proc, 8)
        idx = [f[1] for _, f in got]
        assert idx == sorted(set(idx))  # strictly newer each time (older ones skipped, never repeated)
        for t_read, (img, _i, t_capture, truth, render_s) in got:
            assert img.shape == (720, 1280, 3) and img.dtype == np.uint8 and img.flags.owndata
            # never delivered before a real camera could have: exposure + transport delay
            assert t_read >= t_capture + 0.03 - 1e-4
            assert render_s > 0
            # the truth is the trajectory's, at the exposure time the frame is stamped with
            assert np.allclose(truth.T_cam_ct, layout.T_cam_ct(motion, t_capture), atol=1e-9)
            assert abs(truth.t_s - t_capture) < 1e-9
        # the image shows the balls where the truth says (green balls on skin: G channel dominates)
        img, truth = got[-1][1][0], got[-1][1][3]
        c = np.round(truth.ellipse_centres_px[truth.visible][0]).astype(int)
        b, g, r = img[c[1], c[0]].astype(int)
        assert g > r and g > b
    finally:
        proc.close()
    assert not proc.alive()


def test_a_frame_overwritten_while_read_is_dropped_never_torn():
    proc, _, _ = _camera()
    proc.start(ready_timeout_s=T_STATE)
    try:
        _frames(proc, 1)
        shm = proc._shm
        # freeze the renderer's view: pretend the newest frame is one whose slot is being rewritten
        ctrl = np.ndarray((8,), np.int64, shm.buf, 0)
        newest = int(ctrl[0]) + 10 * SLOTS
        meta = np.ndarray((4,), np.int64, shm.buf, _slot_layout(proc.size, newest % SLOTS)[0])
        ctrl[1] = 1  # stop the child so it cannot repair the slot meanwhile
        proc._proc.join(T_STATE)
        meta[0] = -1  # "being written"
        ctrl[0] = newest
        assert proc.next_frame(0.0) is None
        del ctrl, meta
    finally:
        proc.close()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread scheduling is Linux's")
def test_a_thread_that_inherited_a_raised_priority_drops_it():
    """A server started under ``chrt -f`` or ``nice -n -5``: the pipeline thread and the camera
    process drop what they inherited (lowering is always allowed) and never raise it."""
    import threading

    out = {}

    def run():
        try:  # raise this thread as an inherited priority would be (root only)
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), -5)
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(3))
            out["raised"] = os.sched_getscheduler(0) == os.SCHED_FIFO
        except PermissionError:
            out["raised"] = False
        out["answer"] = normal_priority(0)
        out["after"] = (os.sched_getscheduler(0), os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))
        out["lower"] = normal_priority(4)
        out["lowered"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
        out["again"] = normal_priority(0)  # never raises it back
        out["still"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    th = threading.Thread(target=run)
    th.start()
    th.join()
    assert out["after"] == (os.SCHED_OTHER, 0), out
    if out["raised"]:
        assert "dropped an inherited real-time policy" in out["answer"]
    assert out["lowered"] == 4 and out["lower"] == "normal priority (nice 4)"
    assert out["still"] == 4 and "\n" not in out["again"]


CHILD = """
import json, os, sys, time
from monotracker.engine import Session, SessionConfig
from monotracker.sim.phantom import default_phantom

def threads(pid):
    out = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            out.append([int(tid), os.sched_getscheduler(int(tid)), os.getpriority(os.PRIO_PROCESS, int(tid))])
        except (ProcessLookupError, PermissionError):
            pass
    return out

def main():
    home = sys.argv[1]
    s = Session(SessionConfig(home=home, clock="sim"))
    ph = default_phantom()
    for c in ph.fiducial_centres_lps:
        assert s.add_fiducial(c, ph.fiducial_radius_mm).ok
    assert s.confirm_fiducials().ok and s.use_sample_plan().ok
    s.shutdown()
    s = Session(SessionConfig(home=home, clock="real", camera="sim", trajectory="still"))
    try:
        s.start()
        s.wait_for_job(120)
        assert s.start_camera().ok
        assert s.connect_robot().ok
        t0 = time.monotonic()
        while not (s.snapshot().pose and s.snapshot().pose.trusted):
            assert time.monotonic() - t0 < 120, "no trusted pose"
            time.sleep(0.05)
        rig = s._loop.camera.rig
        smp = rig.latest_sample()
        proc = s._loop.robot.rig.proc
        print(json.dumps({"priority": rig.priority, "engine": s._loop.driver.priority, "stages": smp.stages,
                          "camera_pid": rig._camproc.pid if rig._camproc is not None else None,
                          "control_pid": proc.pid, "control": proc.priority,
                          "engine_threads": threads(os.getpid()),
                          "camera_threads": threads(rig._camproc.pid) if rig._camproc is not None else [],
                          "control_threads": threads(proc.pid),
                          "codes": [a.code for a in s.snapshot().alerts]}))
    finally:
        s.shutdown()

if __name__ == "__main__":
    main()
"""


def _run_child(tmp_path, as_nobody: bool):
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    home = tmp_path / "home"
    home.mkdir()
    env = dict(os.environ, PYTHONPATH=str(ROOT / "app"), MONOTRACKER_HOME=str(home))
    pre = None
    if as_nobody:
        os.chmod(tmp_path, 0o777)
        os.chmod(home, 0o777)
        os.chmod(script, 0o644)

        def pre():
            os.setgid(65534)
            os.setuid(65534)
    p = subprocess.run([sys.executable, str(script), str(home)], capture_output=True, text=True, encoding="utf-8", errors="replace", env=env, cwd=ROOT,
                       timeout=600, preexec_fn=pre)
    assert p.returncode == 0, p.stderr[-3000:]
    import json

    return json.loads(p.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread scheduling is Linux's")
def test_real_time_is_for_the_control_process_only(tmp_path):
    """The OS's view of every thread: the engine process (web server, pipeline, engine loop) and
    the camera process at normal priority; the control process at SCHED_FIFO where allowed."""
    r = _run_child(tmp_path, as_nobody=False)
    assert r["camera_pid"] is not None
    st = r["stages"]
    # the frame reached the pipeline no sooner than the modelled transport delay after exposure
    assert st["arrived_s"] >= 0.030 - 1e-4 and st["estimate_s"] > 0 and st["detect_s"] > 0
    for name in ("engine_threads", "camera_threads"):
        assert r[name], name
        for tid, policy, nice in r[name]:
            assert policy == os.SCHED_OTHER and nice >= 0, f"{name}: thread {tid} runs at policy {policy}, nice {nice}"
    assert r["priority"].startswith("normal priority") and r["engine"].startswith("normal priority")
    if r["control"].startswith("SCHED_FIFO"):  # where the OS grants it (root, CAP_SYS_NICE)
        assert all(policy == os.SCHED_FIFO for _, policy, _ in r["control_threads"]), r["control_threads"]
        assert "control_priority" not in r["codes"]
    else:
        assert "control_priority" in r["codes"]
    assert "pose_priority" not in r["codes"]


@pytest.mark.skipif(not hasattr(os, "setuid") or os.geteuid() != 0, reason="needs root to start a child as nobody")
def test_an_unprivileged_session_tracks_and_says_the_control_process_is_not_real_time(tmp_path):
    """As a user the OS refuses SCHED_FIFO: the session still runs, and the control process's
    warning says so; the pipeline asks for nothing it could be refused."""
    try:
        r = _run_child(tmp_path, as_nobody=True)
    except PermissionError:
        pytest.skip("nobody cannot run this checkout's Python (a private folder)")
    except AssertionError as exc:
        if "Permission denied" in str(exc):
            pytest.skip("nobody cannot read this checkout (a private folder)")
        raise
    assert "refused" in r["control"] and "control_priority" in r["codes"]
    assert r["priority"].startswith("normal priority") and "pose_priority" not in r["codes"]


def test_camera_process_that_cannot_be_spawned_says_why(monkeypatch):
    """A spawn refused before the child exists (here: the OS refuses the fork) is reported as the
    product's error naming the cause, and nothing is left behind; it used to surface as
    ``AssertionError: can only join a started process`` from the clean-up (the cause lost)."""
    import multiprocessing.process as mpp

    from monotracker.errors import MonoTrackerError

    def refuse(self):
        raise OSError("Resource temporarily unavailable")

    monkeypatch.setattr(mpp.BaseProcess, "start", refuse)
    proc, _layout, _motion = _camera()
    with pytest.raises(MonoTrackerError, match="failed to start .*OSError"):
        proc.start(ready_timeout_s=5.0)
    assert not proc.alive() and proc.next_frame(0.0) is None
