"""Frame sources: video, folder, camera errors, the simulator's faults and the watchdog."""

import time

import cv2
import numpy as np
import pytest

from monotracker.errors import InputError
from monotracker.sim.camera_sim import SimulatedCamera
from monotracker.vision.frames import (CameraDisconnected, Frame, FrameWatchdog, ImageFolderSource, OpenCVCamera,
                                       VideoFileSource, open_source)


def _write_video(path, frames):
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (frames[0].shape[1], frames[0].shape[0]))
    assert vw.isOpened()
    for f in frames:
        vw.write(f)
    vw.release()


def test_video_file_frames(tmp_path):
    imgs = [np.full((120, 160, 3), 20 * i, np.uint8) for i in range(5)]
    p = tmp_path / "clip.avi"
    _write_video(p, imgs)
    with VideoFileSource(p) as src:
        frames = list(src)
    assert [f.index for f in frames] == list(range(5))
    assert all(f.image.shape == (120, 160, 3) and f.image.dtype == np.uint8 for f in frames)
    assert abs(int(frames[3].image.mean()) - 60) <= 3
    assert all(b.t_capture >= a.t_capture for a, b in zip(frames, frames[1:]))


def test_corrupt_video_is_a_clear_error(tmp_path):
    p = tmp_path / "broken.avi"
    p.write_bytes(b"RIFF\x00\x00\x00\x00AVI garbage" + bytes(range(256)) * 20)
    with pytest.raises(InputError, match="broken.avi"):
        VideoFileSource(p)
    with pytest.raises(InputError, match="not found"):
        VideoFileSource(tmp_path / "nothing.mp4")


def test_image_folder(tmp_path):
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i:02d}.png"), np.full((10, 12), 40 * i, np.uint8))
    with open_source(str(tmp_path)) as src:
        assert isinstance(src, ImageFolderSource)
        frames = list(src)
    assert len(frames) == 3 and frames[2].image.shape == (10, 12, 3) and frames[2].image[0, 0, 0] == 80
    (tmp_path / "f03.png").write_bytes(b"not a png")
    src = ImageFolderSource(tmp_path)
    with pytest.raises(InputError, match="f03.png"):
        list(src)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no .png"):
        ImageFolderSource(empty)


def test_missing_camera_is_a_clear_error():
    with pytest.raises(InputError, match="no camera at device index 57"):
        OpenCVCamera(57)


def test_simulated_camera_unplugged_mid_stream():
    cam = SimulatedCamera(disconnect_at_frame=3, seed=1)
    for _ in range(3):
        assert cam.read() is not None
    with pytest.raises(CameraDisconnected, match="disconnected"):
        cam.read()


def test_watchdog_detects_frozen_camera_within_three_frames():
    cam = SimulatedCamera(freeze_at_frame=4, seed=1)
    wd = FrameWatchdog()
    reasons = []
    for _i in range(8):
        reasons.append(wd.feed(cam.read()))
    assert all(r == "" for r in reasons[:5])  # frames 0..4 differ (frame 4 is the last new one)
    assert "frozen" in reasons[6]             # frame 6 = 2nd repeat: 67 ms at 30 fps
    assert reasons[6] and reasons[7]


def test_watchdog_detects_stall():
    wd = FrameWatchdog(max_age_s=0.1)
    wd.feed(Frame(np.zeros((4, 4, 3), np.uint8), time.monotonic(), 0))
    assert wd.check() == ""
    assert "stalled" in wd.check(time.monotonic() + 0.15)


class _FakeCapture:
    """A camera device as OpenCV's VideoCapture shows it: properties that may refuse a change."""

    refuse_autofocus_off = False
    image = np.zeros((720, 1280, 3), np.uint8)

    def __init__(self, *_args):
        self.props = {cv2.CAP_PROP_AUTOFOCUS: 1.0, cv2.CAP_PROP_FOURCC: float(cv2.VideoWriter_fourcc(*"YUYV"))}

    def isOpened(self):
        return True

    def set(self, prop, value):
        if prop == cv2.CAP_PROP_AUTOFOCUS and self.refuse_autofocus_off:
            return False
        self.props[prop] = float(value)
        return True

    def get(self, prop):
        return self.props.get(prop, -1.0)

    def read(self):
        return True, self.image.copy()

    def release(self):
        pass


@pytest.mark.parametrize("refuse, expected", [(False, ""), (True, "on")])
def test_a_camera_device_gets_its_autofocus_turned_off(monkeypatch, refuse, expected):
    """Refocusing changes the focal length (2 % = ~10 mm at the target, unseen): the device's
    autofocus is turned off at open, and a device that refuses says so (``autofocus == "on"``;
    the engine shows ``camera_autofocus``). Before: autofocus was left as the driver had it."""
    monkeypatch.setattr(_FakeCapture, "refuse_autofocus_off", refuse)
    monkeypatch.setattr(cv2, "VideoCapture", _FakeCapture)
    cam = OpenCVCamera(0)
    try:
        assert cam.autofocus == expected
        assert cam._cap.get(cv2.CAP_PROP_AUTOFOCUS) == (1.0 if refuse else 0.0)
    finally:
        cam.close()
