"""The live pose stream: frames -> detected balls -> registration -> timestamped PoseEstimate.

Two layers, so that the logic is testable without threads:

* :class:`PoseTracker` -- ``process(frame) -> PoseEstimate`` for one frame: detect the balls,
  register them to the CT fiducials (previous valid pose as prior; the registration falls back
  to its full correspondence search by itself when the prior no longer explains the image),
  gate the result, assign each CT fiducial a status and raise alerts.
* :class:`PoseStream` -- runs a tracker on a :class:`~monotracker.vision.frames.FrameSource`
  in its own daemon thread (never the UI thread). ``start()``, ``stop()``, ``subscribe(cb)``
  (``cb(estimate)`` called from the stream thread; keep it short, post to your own queue),
  ``latest()``. A monitor thread checks the :class:`~monotracker.vision.frames.FrameWatchdog`
  every 20 ms, so a camera that freezes (identical frames), is late (``read()`` blocks for longer
  than ``watchdog.max_age_s`` = 0.1 s: ``camera_late``) or stops delivering (``read()`` blocks for
  longer than ``watchdog.stall_s`` = 0.5 s: ``camera_stalled``, or raises) is published as an
  invalid estimate within that time (+ one 20 ms monitor tick). The stall check applies to live sources
  after their first frame (not to files and folders, which are read on demand). Time spent processing a frame does not
  count as a stall: only time spent waiting inside ``read()`` does.

The per-frame logic (validity rules, alert codes, per-fiducial status) is
:mod:`.pose_tracker`; its names are re-exported here.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

import numpy as np

from monotracker.errors import MonoTrackerError

from .frames import CameraDisconnected, FrameSource, FrameUnreadable, FrameWatchdog
from .pose_estimate import (CAMERA_CODES, MOVED, NEWLY_LOST, OCCLUDED, SEEN,  # noqa: F401 - public names
                            UNKNOWN, PoseEstimate)
from .pose_tracker import PoseTracker
from .tracker_config import TrackerConfig  # noqa: F401 - a public name of the pose stream

log = logging.getLogger(__name__)


class PoseStream:
    """Runs a :class:`PoseTracker` on a frame source in a background thread.

    ``latest()`` returns the newest :class:`PoseEstimate` (or None); ``subscribe(cb)`` adds a
    callback run in the stream thread for every estimate; ``stop()`` joins the threads and
    closes the source. ``estimates`` counts published estimates; ``camera_state`` is the
    source's last state ("ok", "frozen", "late", "stalled", "disconnected", "ended").

    Args:
        source: any :class:`FrameSource` (camera, video file, image folder, replay, the
            digital twin's simulated camera).
        tracker: the :class:`PoseTracker`; None asks the source for one (``source.pose_tracker()``:
            a source that knows its scene, as the simulated camera knows its phantom).
        watchdog: freeze / stall detection (:class:`FrameWatchdog`); defaults when None.
        close_source: close ``source`` in :meth:`stop`.

    Raises:
        MonoTrackerError: ``tracker`` is None and the source cannot make one.
    """

    def __init__(self, source: FrameSource, tracker: PoseTracker | None = None,
                 watchdog: FrameWatchdog | None = None, close_source: bool = True):
        if tracker is None:
            make = getattr(source, "pose_tracker", None)
            if make is None:
                raise MonoTrackerError("PoseStream needs a tracker (fiducials and camera calibration) for this source")
            tracker = make()
        self.source = source
        self.tracker = tracker
        self.watchdog = watchdog or FrameWatchdog()
        self.close_source = close_source
        self._subs: list[Callable[[PoseEstimate], None]] = []
        self._latest: PoseEstimate | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._monitor: threading.Thread | None = None
        self._fault = ""           # camera fault already published (avoid repeats)
        self._fault_lock = threading.Lock()
        self._read_since: float | None = None   # monotonic time the pending read() began
        self._last_index = -1
        self.estimates = 0
        self._run_frames = 0               # frames the tracker judged (stream thread only)
        self._run_trusted = 0              # of those, with a trusted pose
        self._last_refusal = ""            # why the tracker's last frame had no trusted pose ("" when it had)
        self.camera_state = "ok"

    # ------------------------------------------------------------------ API
    def subscribe(self, callback: Callable[[PoseEstimate], None]) -> None:
        """Call ``callback(estimate)`` for every published estimate, from the stream thread
        (keep it short: post to your own queue)."""
        with self._lock:
            self._subs.append(callback)

    def latest(self) -> PoseEstimate | None:
        """The newest published :class:`PoseEstimate`, or None before the first one."""
        with self._lock:
            return self._latest

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> "PoseStream":
        """Start the stream and watchdog threads (no-op when running); returns ``self``."""
        if self.running:
            return self
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="pose-stream", daemon=True)
        self._monitor = threading.Thread(target=self._watch, name="pose-stream-watchdog", daemon=True)
        self._thread.start()
        self._monitor.start()
        return self

    def set_target(self, target_ct: np.ndarray | None) -> None:
        """Planned target (CT mm) for ``predicted_tre_mm``; takes effect from the next frame."""
        self.tracker.set_target(target_ct)

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the threads and close the source (if ``close_source``). A ``read()`` that blocks
        (stalled camera) is unblocked by closing the source after a short grace period."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(0.2)
            if self._thread.is_alive() and self.close_source:
                try:
                    self.source.close()
                except Exception:
                    log.exception("closing the frame source failed")
        for t in (self._thread, self._monitor):
            if t is not None:
                t.join(timeout)
        if self.close_source:
            try:
                self.source.close()
            except Exception:  # closing a dead camera must not raise at shutdown
                log.exception("closing the frame source failed")

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()
        return False

    # ------------------------------------------------------------------ threads
    def _publish(self, est: PoseEstimate) -> None:
        with self._lock:
            self._latest = est
            self.estimates += 1
            subs = list(self._subs)
        for cb in subs:
            try:
                cb(est)
            except Exception:  # a broken subscriber must not kill tracking
                log.exception("pose stream subscriber failed")

    def _fault_estimate(self, camera: str, reason: str) -> None:
        with self._fault_lock:
            if self._fault == camera:
                return
            self._fault = camera
            self.camera_state = camera
            est = self.tracker.camera_fault(self._last_index, time.monotonic(), camera, reason)
        self._publish(est)

    def _ended_reason(self) -> str:
        """The operator's line when a video or a folder ends: how many frames it gave and, where
        its last frame had no trusted pose, why (a grayscale video would otherwise end on
        "camera stream ended" alone, the reason its frames were refused gone with the condition
        the end replaces)."""
        n, why = self._run_frames, self._last_refusal
        if n == 0:
            return "camera stream ended before its first frame"
        said = f"camera stream ended after {n} frame{'s' if n != 1 else ''}"
        if not why:
            return said
        if self._run_trusted == 0:
            return f"{said}, none with a trusted pose (the last: {why})"
        return f"{said}; the last had no trusted pose ({why})"

    def _run(self) -> None:
        while not self._stop.is_set():
            self._read_since = time.monotonic()
            try:
                frame = self.source.read()
            except FrameUnreadable as exc:
                # one bad frame (corrupt image, decode error): report it, go on with the next
                if not self._stop.is_set():
                    self._fault_estimate("unreadable", f"frame unreadable: {exc}")
                    with self._fault_lock:
                        self._fault = ""   # each unreadable frame is its own event
                continue
            except CameraDisconnected as exc:
                if not self._stop.is_set():     # closing the source on stop() is not a fault
                    self._fault_estimate("disconnected", f"camera disconnected: {exc}")
                return
            except MonoTrackerError as exc:
                if not self._stop.is_set():
                    self._fault_estimate("disconnected", f"camera error: {exc}")
                return
            finally:
                self._read_since = None
            if frame is None:
                self._fault_estimate("ended", self._ended_reason())
                return
            self._last_index = frame.index
            frozen = self.watchdog.feed(frame)
            if frozen:
                self._fault_estimate("frozen", frozen)
                continue
            with self._fault_lock:
                self._fault = ""
                self.camera_state = "ok"
            try:
                est = self.tracker.process(frame)
            except Exception as exc:  # report, keep the stream alive
                log.exception("pose tracking failed on frame %d", frame.index)
                est = PoseEstimate(False, f"internal error: {type(exc).__name__}: {exc}", frame.index,
                                   frame.t_capture, time.monotonic(), alerts=[f"internal error: {exc}"],
                                   code="pose_lost")
            self._run_frames += 1
            self._run_trusted += bool(est.ok)
            self._last_refusal = "" if est.ok else (est.reason or est.code or "no trusted pose").rstrip(".")
            self._publish(est)
            after = getattr(self.tracker, "after_publish", None)
            if after is not None:
                after()   # a due frame's camera-motion check, now that its pose is out (never raises)

    def _watch(self) -> None:
        while not self._stop.wait(0.02):
            if not self._thread.is_alive():
                return
            since = self._read_since
            # a stall is a live camera that stopped delivering: not the start-up before its first
            # frame (opening, auto-exposure; nothing to trust yet), and never a file or a folder
            # (read as fast as frames are processed)
            if since is not None and self._last_index >= 0 and getattr(self.source, "live", True):
                age = time.monotonic() - since
                if age > self.watchdog.stall_s:
                    self._fault_estimate("stalled", f"camera stalled: no new frame for {1000 * age:.0f} ms")
                elif age > self.watchdog.max_age_s:
                    self._fault_estimate("late", f"camera late: no new frame for {1000 * age:.0f} ms (the "
                                         "camera is still read; the machine may be busy)")
