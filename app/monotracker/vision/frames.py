"""Frame sources: one interface for a live camera, a video file, an image folder and the simulator.

Every source has ``read() -> Frame | None`` (``None`` = the source ended normally, e.g. the
end of a video; a camera that stops answering raises :class:`CameraDisconnected`),
``close()``, and works as a context manager. ``Frame.image`` is BGR uint8 (h, w, 3),
``t_capture`` is ``time.monotonic()`` seconds at capture, ``index`` counts frames from 0, and
``truth`` is set only by the simulator (:class:`monotracker.sim.camera_sim.FrameTruth`).

Opening problems (no such camera, unreadable video, empty folder) raise :class:`InputError`
with one line; one bad frame later on raises :class:`FrameUnreadable` (an ``InputError``) and
the source continues with the next frame. :class:`FrameWatchdog` turns "frames stopped coming" or "the same frame again
and again" into a clear status within 0.1 s (see its docstring).

``compression`` says when the frames come through a lossy coding (a camera sending MJPEG, JPEG
files, a known lossy video codec): ball centres then err up to ~2.5x more (independent renders,
1.5 px defocus, Bayer: 0.06 px uncompressed, 0.09 px at JPEG 95, 0.15 px at JPEG 85;
``benchmarks/independent_optics.py``), so the engine shows it as a warning while the camera runs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from monotracker.errors import InputError, MonoTrackerError


class CameraDisconnected(MonoTrackerError):
    """The camera stopped delivering frames (unplugged, driver crashed)."""


class FrameUnreadable(InputError):
    """One frame could not be read (corrupt image file, undecodable video frame, wrong pixel
    type); the source itself goes on: the next ``read()`` returns the next frame. The pose
    stream reports it under the alert code ``frame_unreadable``."""


@dataclass
class Frame:
    """One image: ``image`` BGR uint8 (h, w, 3); ``t_capture`` monotonic s; ``index`` from 0;
    ``truth`` the simulator's ground truth (``None`` for real sources)."""

    image: np.ndarray
    t_capture: float
    index: int
    truth: Any = None


class FrameSource:
    """Base class: subclasses implement ``_read_image() -> np.ndarray | None`` and ``_release()``."""

    name = "frames"
    #: a live source delivers frames in real time (a camera): reading it may stall. A file or a
    #: folder is read as fast as the reader asks, so a slow read is no camera fault.
    live = True
    #: "" (uncompressed, or not known) or the lossy coding the frames come through, as the user
    #: would name it ("MJPEG", "JPEG files", "video codec 'avc1'")
    compression = ""
    #: "on" when the camera's autofocus is on and could not be turned off (its focal length, and
    #: so the calibration, changes whenever it refocuses); "" otherwise
    autofocus = ""

    def __init__(self):
        self._index = 0
        self._closed = False

    def read(self) -> Frame | None:
        if self._closed:
            raise MonoTrackerError(f"{self.name}: read() after close()")
        img = self._read_image()
        if img is None:
            return None
        img = _as_bgr(img)
        f = Frame(img, time.monotonic(), self._index)
        self._index += 1
        return f

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._release()

    def _read_image(self):  # pragma: no cover - abstract
        raise NotImplementedError

    def _release(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def __iter__(self):
        while True:
            f = self.read()
            if f is None:
                return
            yield f


#: a frame is grayscale when no sampled pixel's colour channels differ by more than this (grey
#: levels; JPEG's chroma rounding of a grey picture stays within 2) while the frame has content
#: (its 1-99 % grey-level spread at least ``GREY_MIN_CONTRAST``: a black or blank frame says nothing)
GREY_CHANNEL_SPREAD = 3
GREY_MIN_CONTRAST = 20


def grayscale_problem(image: np.ndarray) -> str:
    """'' for a colour frame, else one line saying that the frame is grayscale and what to do.

    The fiducial detectors find the balls by their colour; a monochrome (or IR) camera, a
    grayscale video or a folder of grayscale images gives frames with one channel, or three
    equal ones after conversion, in which no ball can ever be found: without this check the
    operator sees "0 fiducials detected" and looks for a covered patch. Cost: a 1-in-16 pixel
    sample for a colour frame (~0.05 ms at 1280x720), a 1-in-4 one for a grey-looking frame."""
    img = np.asarray(image)
    why = ("frames are grayscale ({}): the balls are found by their colour, so none can be found; "
           "use a colour camera (not a monochrome or infrared one) or colour frames")
    if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1):
        return why.format("one channel")
    if img.ndim != 3 or img.shape[2] < 3:
        return ""
    for step in (16, 4):   # a 1-in-16 sample (a subset of the 1-in-4 one) settles a colour frame at once
        s = img[::step, ::step, :3].astype(np.int16)
        spread = np.maximum(np.abs(s[..., 0] - s[..., 1]), np.abs(s[..., 1] - s[..., 2]))
        if spread.max() > GREY_CHANNEL_SPREAD:
            return ""
    lo, hi = np.percentile(s[..., 1], (1, 99))
    if hi - lo < GREY_MIN_CONTRAST:
        return ""                   # black, blank or saturated: nothing to say about its colour
    return why.format("the three colour channels are equal")


def _as_bgr(img: np.ndarray) -> np.ndarray:
    if img.dtype != np.uint8:
        raise FrameUnreadable(f"frame has dtype {img.dtype}, expected 8-bit images")
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


#: FourCC codes of JPEG-coded frames (what most USB cameras send at 720p and 30 fps)
JPEG_FOURCC = frozenset({"MJPG", "JPEG", "AVDJ", "DMB1"})
#: FourCC codes of lossy video codecs (H.264/5, MPEG-4 part 2, VP8/9, AV1, WMV, Theora). Only
#: these are named: a code not listed (raw V4L2 formats such as RGB3, BA81, NV21, lossless FFV1)
#: makes no claim
LOSSY_VIDEO_FOURCC = frozenset({"H264", "AVC1", "X264", "DAVC", "HEVC", "H265", "HVC1", "HEV1", "X265",
                                "MP4V", "FMP4", "XVID", "DIVX", "DX50", "MP42", "MP43", "MPG4", "MPG1",
                                "MPG2", "PIM1", "VP80", "VP90", "VP08", "VP09", "AV01", "WMV1", "WMV2",
                                "WMV3", "WVC1", "THEO", "H263", "FLV1"})


def fourcc_name(code: float) -> str:
    """The four characters of OpenCV's ``CAP_PROP_FOURCC`` value ('' when 0, negative (a
    backend without the property gives -1) or not printable ASCII)."""
    n = int(code) if np.isfinite(code) else 0
    if n <= 0:
        return ""
    chars = "".join(chr((n >> (8 * i)) & 0xFF) for i in range(4))
    return chars if chars.isascii() and chars.isprintable() else ""


def lossy_coding(fourcc: str) -> str:
    """The name of the lossy coding behind FourCC ``fourcc`` for a message ("MJPEG" or "video
    codec 'avc1'"); '' when it is uncompressed, lossless or not known to be lossy."""
    code = (fourcc or "").upper()
    if code in JPEG_FOURCC:
        return "MJPEG"
    if code in LOSSY_VIDEO_FOURCC:
        return f"video codec {fourcc.strip()!r}"
    return ""


class OpenCVCamera(FrameSource):
    """A live camera by OpenCV device index. ``read()`` raises :class:`CameraDisconnected` when
    the device stops answering (``cv2.VideoCapture.read`` fails). At open its autofocus is turned
    off (:func:`lock_focus`); ``autofocus`` is "on" when the camera refused."""

    def __init__(self, device: int = 0, width: int | None = 1280, height: int | None = 720,
                 backend: int = cv2.CAP_ANY):
        super().__init__()
        self.name = f"camera {device}"
        self._cap = cv2.VideoCapture(int(device), backend)
        if not self._cap.isOpened():
            self._cap.release()
            raise InputError(f"no camera at device index {device}: is it plugged in and free "
                             "(not used by another program)?")
        if width and height:
            self._cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
            self._cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        self.compression = lossy_coding(fourcc_name(self._cap.get(cv2.CAP_PROP_FOURCC)))
        self.autofocus = lock_focus(self._cap)

    def _read_image(self):
        ok, img = self._cap.read()
        if not ok or img is None:
            raise CameraDisconnected(f"{self.name} stopped delivering frames (unplugged?)")
        return img

    def _release(self):
        self._cap.release()


def lock_focus(cap) -> str:
    """Turn a camera's autofocus off (``cv2.CAP_PROP_AUTOFOCUS`` = 0) and say what came of it:
    "" (off now, or the camera reports no autofocus: a fixed-focus camera) or "on" (the camera
    reports autofocus on after the request: the driver refused).

    Why: refocusing changes the focal length (focus breathing, ~1-3 % on webcam lenses), and a
    focal length 2 % off puts the target ~10 mm off with nothing in the residuals to show it
    (``vision/calibration_check.py``); the calibration only holds at the focus it was made at."""
    try:
        cap.set(cv2.CAP_PROP_AUTOFOCUS, 0)
        now = float(cap.get(cv2.CAP_PROP_AUTOFOCUS))
    except cv2.error:
        return ""
    return "on" if now > 0 else ""


class VideoFileSource(FrameSource):
    """Frames of a video file; ``read()`` returns ``None`` at the end. A file OpenCV cannot decode
    raises :class:`InputError` at open (or at the first frame)."""

    live = False

    def __init__(self, path: str | Path, loop: bool = False):
        super().__init__()
        path = Path(path)
        self.name = f"video {path.name}"
        if not path.is_file():
            raise InputError(f"video file not found: {path}")
        self._cap = cv2.VideoCapture(str(path))
        self._loop = loop
        if not self._cap.isOpened():
            self._cap.release()
            raise InputError(f"cannot decode video {path.name} (corrupt file or unsupported codec)")
        ok, first = self._cap.read()
        if not ok or first is None:
            self._cap.release()
            raise InputError(f"video {path.name} holds no readable frame (corrupt or empty file)")
        self._pending = first
        self.fps = float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.compression = lossy_coding(fourcc_name(self._cap.get(cv2.CAP_PROP_FOURCC)))

    def _read_image(self):
        if self._pending is not None:
            img, self._pending = self._pending, None
            return img
        ok, img = self._cap.read()
        if not ok:
            # a frame that fails to decode before the end of the stream is unreadable, not the end
            pos = int(self._cap.get(cv2.CAP_PROP_POS_FRAMES) or 0)
            count = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            if 0 < pos + 1 < count:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, pos + 1)
                raise FrameUnreadable(f"{self.name}: frame {pos} cannot be decoded")
        if not ok and self._loop:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            ok, img = self._cap.read()
        return img if ok else None

    def _release(self):
        self._cap.release()


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class ImageFolderSource(FrameSource):
    """Images of a folder in name order (png/jpg/bmp/tif); an unreadable image raises
    :class:`FrameUnreadable` naming it, and the next ``read()`` goes on with the next image."""

    live = False

    def __init__(self, folder: str | Path):
        super().__init__()
        folder = Path(folder)
        self.name = f"folder {folder}"
        if not folder.is_dir():
            raise InputError(f"image folder not found: {folder}")
        self.paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.paths:
            raise InputError(f"image folder {folder} holds no .png/.jpg/.bmp/.tif images")
        self._next = 0
        if any(p.suffix.lower() in (".jpg", ".jpeg") for p in self.paths):
            self.compression = "JPEG files"

    def _read_image(self):
        if self._next >= len(self.paths):
            return None
        p = self.paths[self._next]
        self._next += 1
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise FrameUnreadable(f"cannot read image {p.name} (corrupt or not an image)")
        return img


def open_source(spec: str | int, **kwargs) -> FrameSource:
    """Open a real source from a user spec: an integer or digit string -> camera device, a folder
    -> ImageFolderSource, a file -> VideoFileSource. (The simulated camera is the digital twin's,
    ``monotracker.sim.camera_sim.SimulatedCamera``: vision knows nothing of the simulator.)"""
    if isinstance(spec, int) or (isinstance(spec, str) and spec.isdigit()):
        return OpenCVCamera(int(spec), **kwargs)
    p = Path(spec)
    if p.is_dir():
        return ImageFolderSource(p)
    return VideoFileSource(p, **kwargs)


class FrameWatchdog:
    """Detects a frozen or disconnected camera.

    ``frozen``: the last ``identical_limit`` frames were bit-identical (real sensors always have
    noise, so two identical consecutive frames already mean a stuck driver buffer; we require
    ``identical_limit`` = 2 repeats). ``stalled``: no new frame for ``max_age_s`` (default 0.1 s,
    i.e. 3 frames at 30 fps). ``check(now)`` returns '' when healthy, else a reason. The pose
    stream tells a late frame from a stalled camera by how long its ``read()`` waits: over
    ``max_age_s`` the frame is *late* (the source alive, the machine busy), over ``stall_s``
    (default 0.5 s, 15 frames at 30 fps) the camera has *stalled*.
    Identity is tested on a sparse pixel sample (every 7th row/col) plus a full check only when
    the sample matches, so it costs ~0.1 ms per frame.
    """

    def __init__(self, max_age_s: float = 0.1, identical_limit: int = 2, stall_s: float = 0.5):
        self.max_age_s = max_age_s
        self.stall_s = max(float(stall_s), float(max_age_s))
        self.identical_limit = identical_limit
        self._last_t = None
        self._last_img = None
        self._repeats = 0

    def feed(self, frame: Frame) -> str:
        """Record a new frame; returns '' or the reason it is considered frozen."""
        img = frame.image
        same = (self._last_img is not None and self._last_img.shape == img.shape
                and np.array_equal(self._last_img[::7, ::7], img[::7, ::7])
                and np.array_equal(self._last_img, img))
        self._repeats = self._repeats + 1 if same else 0
        self._last_img = img
        self._last_t = frame.t_capture
        return self.frozen_reason()

    def frozen_reason(self) -> str:
        if self._repeats >= self.identical_limit:
            return f"camera frozen: {self._repeats + 1} identical frames in a row"
        return ""

    def check(self, now: float | None = None) -> str:
        """'' if healthy, else why (frozen or no frame for longer than ``max_age_s``)."""
        now = time.monotonic() if now is None else now
        if self._last_t is not None and now - self._last_t > self.max_age_s:
            return f"camera stalled: no new frame for {1000 * (now - self._last_t):.0f} ms"
        return self.frozen_reason()
