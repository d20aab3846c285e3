"""Frames must match their calibration; poses must be physical; alert codes say what happened.

Truth: the simulator's true pose per frame, OpenCV's own projection (cv2.projectPoints) for the
adapted intrinsics, and images resized/cropped with OpenCV exactly as a binned or cropped sensor
delivers them.
"""

import threading

import cv2
import numpy as np
import pytest

from monotracker.errors import InputError
from monotracker.geometry import apply_transform
from monotracker.sim.camera_sim import SimulatedCamera
from monotracker.sim.phantom import default_phantom
from monotracker.vision.camera_model import default_camera
from monotracker.vision.frames import Frame, ImageFolderSource, VideoFileSource
from monotracker.vision.pose_checks import physical_problem, weak_geometry
from monotracker.vision.pose_stream import PoseStream, PoseTracker

PH = default_phantom()


def _tracker(model):
    return PoseTracker(PH.fiducial_centres_lps, model, radius_mm=PH.fiducial_radius_mm,
                       target_ct=PH.sample_target_lps)


def _target_error(T, T_true):
    t = PH.sample_target_lps
    return float(np.linalg.norm(apply_transform(T, t) - apply_transform(T_true, t)))


@pytest.fixture(scope="module")
def sim_frames():
    cam = SimulatedCamera(seed=2, max_frames=4)
    return cam.camera, list(cam)


# ---------------------------------------------------------------- adapted intrinsics
def test_scaled_and_cropped_models_match_opencv_on_transformed_pixels():
    cam = default_camera()
    rng = np.random.default_rng(0)
    P = np.column_stack([rng.uniform(-150, 150, 50), rng.uniform(-90, 90, 50), rng.uniform(400, 700, 50)])
    px, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    px = px.reshape(-1, 2)
    half = cam.adapted("bin:2")
    assert half.image_size == (640, 360)
    # a pixel centre u of the full image lies at (u + 0.5) / 2 - 0.5 in the 2x2-binned one
    np.testing.assert_allclose(half.project(P), (px + 0.5) / 2 - 0.5, atol=1e-9)
    crop = cam.adapted("crop:160,100,960,520")
    assert crop.image_size == (960, 520)
    np.testing.assert_allclose(crop.project(P), px - [160, 100], atol=1e-9)
    for bad in ("bin:0", "crop:0,0,2000,720", "zoom:2", "crop:1,2,3"):
        with pytest.raises(InputError):
            cam.adapted(bad)


# ---------------------------------------------------------------- frame size
def test_half_resolution_frames_are_refused_and_accepted_once_declared_binned(sim_frames):
    model, frames = sim_frames
    small = [Frame(cv2.resize(f.image, (640, 360), interpolation=cv2.INTER_AREA), f.t_capture, f.index, f.truth)
             for f in frames]
    tr = _tracker(model)
    ests = [tr.process(f) for f in small]
    assert not any(e.ok for e in ests) and all(e.T_cam_ct is None for e in ests)
    assert all(e.code == "frame_size" for e in ests)
    assert "640x360" in ests[0].reason and "1280x720" in ests[0].reason and "bin:N" in ests[0].reason
    assert len(ests[0].alerts) == 1 and not ests[1].alerts      # one alert per episode
    # the user says it is the same sensor binned 2x2: scaled explicitly, the pose is right
    tr2 = _tracker(model.adapted("bin:2"))
    ests = [tr2.process(f) for f in small]
    assert all(e.ok for e in ests), [e.reason for e in ests]
    assert max(_target_error(e.T_cam_ct, e.truth.T_cam_ct) for e in ests) < 1.0


def test_cropped_video_is_refused_and_accepted_with_the_crop_declared(sim_frames, tmp_path):
    model, frames = sim_frames
    x0, y0, w, h = 160, 100, 960, 520
    path = tmp_path / "cropped.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (w, h))
    assert vw.isOpened()
    for f in frames:
        vw.write(np.ascontiguousarray(f.image[y0:y0 + h, x0:x0 + w]))
    vw.release()

    tr = _tracker(model)
    with VideoFileSource(path) as src:
        ests = [tr.process(f) for f in src]
    assert len(ests) == len(frames)
    assert not any(e.ok for e in ests) and all(e.code == "frame_size" for e in ests)
    assert "960x520" in ests[0].reason
    tr2 = _tracker(model.adapted(f"crop:{x0},{y0},{w},{h}"))
    with VideoFileSource(path) as src:
        ests = [tr2.process(f) for f in src]
    assert all(e.ok for e in ests), [e.reason for e in ests]
    errs = [_target_error(e.T_cam_ct, f.truth.T_cam_ct) for e, f in zip(ests, frames)]
    assert max(errs) < 1.0


# ---------------------------------------------------------------- physical sanity
def test_physical_check_refuses_impossible_poses(sim_frames):
    model, frames = sim_frames
    T = frames[0].truth.T_cam_ct
    X = PH.fiducial_centres_lps
    f = model.K[0, 0]
    R = PH.fiducial_radius_mm
    z = apply_transform(T, X)[:, 2]
    true_minor = f * R / np.sqrt(z**2 - R**2)          # the balls' image size at their true depth
    idx = list(range(len(X)))
    assert physical_problem(T, X, R, f, idx, true_minor) == ""
    far = T.copy()
    far[:3, 3] *= 6.0                                   # head ~3 m away (a wrong-scale calibration)
    assert "mm from the camera" in physical_problem(far, X, R, f, idx, true_minor / 6)
    behind = np.diag([1.0, -1.0, -1.0, 1.0]) @ T        # the same pose turned 180 deg: all behind
    assert "behind the camera" in physical_problem(behind, X, R, f, idx, true_minor)
    assert "size" in physical_problem(T, X, R, f, idx, true_minor / 2)   # balls half the size they must be


def test_weak_geometry_names_the_problem():
    X = PH.fiducial_centres_lps
    assert weak_geometry(X, list(range(9))) == ""
    assert "only 3" in weak_geometry(X, [0, 1, 2])
    line = np.array([[0, 0, 0], [10, 0, 0], [20, 0.1, 0], [30, 0, 0.1], [40, 0, 0]], float)
    assert "collinear" in weak_geometry(line, [0, 1, 2, 3, 4])
    plane = np.array([[0, 0, 0], [30, 0, 0], [0, 30, 0], [30, 30, 0.2], [15, 10, 0.1]], float)
    assert "coplanar" in weak_geometry(plane, [0, 1, 2, 3, 4])


# ---------------------------------------------------------------- alert codes of sources
def _collect_until(stream, pred, timeout=60.0):
    got, done = [], threading.Event()

    def cb(e):
        got.append(e)
        if pred(e):
            done.set()

    stream.subscribe(cb)
    stream.start()
    assert done.wait(timeout), [(e.code, e.reason) for e in got]
    stream.stop()
    return got


def test_folder_with_a_corrupt_image_then_its_end(sim_frames, tmp_path):
    model, frames = sim_frames
    for f in frames[:2]:
        cv2.imwrite(str(tmp_path / f"f{f.index:02d}.png"), f.image)
    (tmp_path / "f02.png").write_bytes(b"\x89PNG broken")
    cv2.imwrite(str(tmp_path / "f03.png"), frames[3].image)
    stream = PoseStream(ImageFolderSource(tmp_path), _tracker(model))
    got = _collect_until(stream, lambda e: e.camera == "ended")
    codes = [e.code for e in got]
    assert codes[-1] == "camera_ended" and "ended" in got[-1].reason
    bad = [e for e in got if e.code == "frame_unreadable"]
    assert len(bad) == 1 and "f02.png" in bad[0].reason and bad[0].alerts
    assert "occlusion" not in codes and "camera_freeze" not in codes
    # the stream went on after the unreadable frame: the image after it gave a valid pose
    after = got[codes.index("frame_unreadable") + 1:]
    assert any(e.ok for e in after)


def test_video_end_is_camera_ended(sim_frames, tmp_path):
    model, frames = sim_frames
    path = tmp_path / "v.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, model.image_size)
    for f in frames:
        vw.write(f.image)
    vw.release()
    stream = PoseStream(VideoFileSource(path), _tracker(model))
    got = _collect_until(stream, lambda e: e.camera == "ended")
    assert sum(e.ok for e in got) == len(frames)
    assert got[-1].code == "camera_ended" and not got[-1].ok


# ---------------------------------------------------------------- the engine with a folder source
@pytest.mark.serial  # the engine on the real clock: the serial lane (tests/conftest.py)
def test_engine_folder_source_no_freeze_alarm_and_the_end_is_camera_ended(sim_frames, tmp_path):
    """A folder is read only as fast as frames are processed (first frame: full search), and it
    ends: neither is a camera freeze, and the end is not an occlusion."""
    import time

    from monotracker.engine import Session, SessionConfig

    model, frames = sim_frames
    folder = tmp_path / "frames"
    folder.mkdir()
    for f in frames:
        cv2.imwrite(str(folder / f"f{f.index:02d}.png"), f.image)
    model.save(tmp_path / "cam.yml")
    s = Session(SessionConfig(home=tmp_path / "home", clock="real"))
    try:
        assert s.start().ok
        for c in PH.fiducial_centres_lps:
            assert s.add_fiducial(c, PH.fiducial_radius_mm).ok
        assert s.confirm_fiducials().ok and s.use_sample_plan().ok
        assert s.set_camera(f"folder:{folder}", str(tmp_path / "cam.yml")).ok
        assert s.start_camera().ok
        deadline = time.monotonic() + 60.0
        codes = []
        while time.monotonic() < deadline:
            codes = [a.code for a in s.snapshot().alerts]
            if "camera_ended" in codes:
                break
            time.sleep(0.05)
        assert "camera_ended" in codes, codes
        time.sleep(0.3)                          # the engine watchdog runs every 4 ms: give it time to (not) fire
        codes = [a.code for a in s.snapshot().alerts]
        assert "camera_freeze" not in codes and "occlusion" not in codes, codes
        ended = [a for a in s.snapshot().alerts if a.code == "camera_ended"]
        assert len(ended) == 1 and "ended" in ended[0].message
    finally:
        s.shutdown()


def test_cli_detect_image_refuses_a_size_mismatch_unless_adapted(sim_frames, tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    model, frames = sim_frames
    model.save(tmp_path / "cam.yml")
    cv2.imwrite(str(tmp_path / "small.png"), cv2.resize(frames[0].image, (640, 360), interpolation=cv2.INTER_AREA))
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2] / "app"),
               MONOTRACKER_HOME=str(tmp_path))

    def run(*args):
        return subprocess.run([sys.executable, "-m", "monotracker", "detect-image", "small.png", "--camera", "cam.yml",
                               *args], capture_output=True, text=True, cwd=tmp_path, env=env)

    r = run()
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "640x360" in r.stderr and "1280x720" in r.stderr
    r = run("--adapt", "bin:2", "--json")
    assert r.returncode == 0, r.stderr
    import json

    assert len(json.loads(r.stdout)["fiducials"]) == 9


# ---------------------------------------------------------------- grayscale frames
class _MonoDevice:
    """A monochrome camera as OpenCV may hand it over: 2-D frames (no colour conversion)."""

    def __init__(self, frames):
        from monotracker.vision.frames import FrameSource

        class _Src(FrameSource):
            name = "camera 0"

            def __init__(self, imgs):
                super().__init__()
                self.imgs = list(imgs)

            def _read_image(self):
                return self.imgs.pop(0) if self.imgs else None

        self.src = _Src(frames)


def test_grayscale_frames_are_refused_with_what_to_do(sim_frames, tmp_path):
    """Grayscale frames from a folder (3 equal channels once read), a video and a monochrome
    device (one channel) are refused as grayscale, one line; before, they ran as frames in
    which "0 fiducials" were detected (code ``occlusion``), which sends the operator looking
    for a covered patch."""
    model, frames = sim_frames
    greys = [cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY) for f in frames]
    folder = tmp_path / "grey"
    folder.mkdir()
    for i, g in enumerate(greys):
        cv2.imwrite(str(folder / f"f{i}.png"), g)
    video = tmp_path / "grey.avi"
    vw = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30, (1280, 720))
    for g in greys:
        vw.write(cv2.cvtColor(g, cv2.COLOR_GRAY2BGR))
    vw.release()
    for src in (ImageFolderSource(folder), VideoFileSource(video), _MonoDevice(greys).src):
        tr = _tracker(model)
        with src:
            ests = [tr.process(f) for f in src]
        assert len(ests) == len(frames) and not any(e.ok for e in ests)
        assert all(e.code == "frame_grayscale" for e in ests), [e.code for e in ests]
        assert "grayscale" in ests[0].reason and "colour camera" in ests[0].reason
        assert len(ests[0].alerts) == 1 and not ests[1].alerts       # one alert per episode


def test_colour_frames_are_not_taken_for_grayscale(sim_frames):
    """No false refusal: the simple and the photo-like render, a dark (lens-capped) and a blank
    frame, and the independent renderer's frames."""
    from independent_render import FRAME_K, FRAME_SIZE, render_scene

    from monotracker.vision.frames import grayscale_problem

    model, frames = sim_frames
    assert not any(grayscale_problem(f.image) for f in frames)
    photo, _ = SimulatedCamera(seed=3, optics="photo").render(0.0)
    assert grayscale_problem(photo) == ""
    assert grayscale_problem(np.zeros((720, 1280, 3), np.uint8)) == ""
    assert grayscale_problem(np.full((720, 1280, 3), 128, np.uint8)) == ""
    X = np.array([[0.0, 0, 420], [40, 10, 430], [-45, 30, 410]])
    img, _ = render_scene(np.random.default_rng(0), X, 4.0)
    assert img.shape[:2] == FRAME_SIZE[::-1] and FRAME_K[0, 0] > 0
    assert grayscale_problem(img) == ""
