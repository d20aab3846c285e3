"""The rig for real frame sources: a camera device, a video file, an image folder or a session
recording, through vision's :class:`~monotracker.vision.pose_stream.PoseStream` (real clock only).
Built by the rows ``device`` / ``file`` / ``folder`` / ``replay`` of the table of source kinds
(``rigs/sources.py``), which checked the argument.
"""

from __future__ import annotations

import threading

import numpy as np

from monotracker.engine.rigs.base import CameraRig, PoseSample, estimate_to_sample
from monotracker.engine.rigs.validation import KeepDetections, ValidationSet
from monotracker.errors import MonoTrackerError


class _KeepLatest:
    """A frame-source proxy that remembers the newest frame (for the UI overlay)."""

    def __init__(self, src):
        self.src = src
        self.latest = None

    def read(self):
        f = self.src.read()
        if f is not None:
            self.latest = f
        return f

    def close(self) -> None:
        self.src.close()

    def __getattr__(self, name):
        return getattr(self.src, name)


#: ``colour_clash``: raised when ball-coloured areas too large for a ball cover at least this
#: share of the frame for ``CLASH_FRAMES`` frames in a row, cleared after ``CLASH_CLEAR_FRAMES``
#: frames without (our simulator's OR frames: 0 with blue drapes, 0.26-0.74 with a teal or
#: green-blue one inside the default band)
CLASH_SHARE = 0.02
CLASH_FRAMES = 3
CLASH_CLEAR_FRAMES = 30


class StreamRig(CameraRig):
    """A real frame source through vision's PoseStream (clock="real" only).

    ``camera_adapt``: the user's explicit statement that the camera runs the calibrated sensor
    binned or cropped (``"bin:2"``, ``"crop:X,Y,W,H"``; :meth:`CameraModel.adapted`); frames
    whose size still differs from the calibration are refused by the tracker (``frame_size``).
    The stream watches its own camera (identical frames, a blocked ``read()``, disconnection,
    the end of a file, unreadable frames: each published with its alert code), so the engine's
    frame-interval watchdog is not applied to it (``watches_itself``): a file or folder source
    is read only as fast as frames are processed, which is no freeze."""

    watches_itself = True

    #: its frames show the room: the factory gives its tracker a camera-motion watch
    watches_background = True

    def __init__(self, kind: str, arg: str, calibration_path: str | None, plan, session, camera_adapt: str = "",
                 rules=None):
        """``kind``: ``"device" | "file" | "folder" | "replay"``; ``arg``: the device number or the
        path (checked by the source table); ``rules``: the per-frame trust rules (vision's
        ``TrackerConfig``; None: vision's defaults)."""
        super().__init__()
        from monotracker.vision.camera_model import CameraModel, default_camera
        from monotracker.vision.frames import open_source
        from monotracker.vision.lens_range import short_lens_message
        from monotracker.vision.pose_stream import PoseStream, PoseTracker

        source = f"{kind}:{arg}"
        if kind == "replay":
            from monotracker.vision.replay_source import ReplaySource, calibration_path as recorded_calibration

            replay = ReplaySource(arg, realtime=True)  # refuses an incomplete/corrupt recording (one line)
            calibration_path = calibration_path or str(recorded_calibration(arg))
        if calibration_path:
            model = CameraModel.load(calibration_path)
        else:
            model = default_camera()
            session.alert("warning", "camera_uncalibrated",
                          "no camera calibration given: using nominal intrinsics; registration accuracy is not assured")
        model = model.adapted(camera_adapt)
        self.K, self.dist, self.image_size = model.K, model.dist, tuple(model.image_size)
        self.fiducial_ids = [f.id for f in plan.registration_fiducials()]
        radius = float(np.median([f.radius_mm for f in plan.registration_fiducials()]))
        lens = short_lens_message(model, radius)
        if lens:
            session.alert("warning", "camera_short_lens", lens)
        self.validation = ValidationSet.from_plan(plan, radius)
        try:
            src = replay if kind == "replay" else open_source(int(arg) if kind == "device" else arg)
        except MonoTrackerError:
            raise
        except Exception as exc:  # a camera that will not open is an operator problem
            raise MonoTrackerError(f"cannot open camera {source}: {exc}") from exc
        if getattr(src, "compression", ""):
            advice = ("choose an uncompressed format (e.g. YUYV) or JPEG quality >= 95 if the frame rate allows"
                      if kind == "device" else "record or export the frames losslessly (PNG, FFV1)")
            session.alert("warning", "camera_compressed",
                          f"{src.name} delivers lossy frames ({src.compression}): ball centres err up to ~2.5x "
                          f"more than uncompressed (JPEG 85); {advice}")
        self.detector = KeepDetections(model.K, radius)  # keeps the blobs for the validation fiducials
        tracker = PoseTracker(plan.registration_centres(), model, detector=self.detector, radius_mm=radius,
                              target_ct=plan.target_lps_mm, watch_ct=self.validation.centres_ct, config=rules)
        if model.ball_colour is not None:
            self.detector.set_colour(model.ball_colour)      # learned earlier, saved with the calibration
        self.tracker = tracker
        self.source = _KeepLatest(src)
        self.stream = PoseStream(source=self.source, tracker=tracker)
        self._lock = threading.Lock()
        self._frames: list[float] = []
        self._last_image = None
        self._sample_cache = None
        self._session = session
        self._clash = (False, 0)          # (raised, frames in a row that disagree with it)
        self.stream.subscribe(self._on_estimate)

    def _on_estimate(self, est) -> None:
        # runs on the stream thread right after the frame was processed: the newest frame read is
        # the one this estimate came from (kept with it for session recording)
        fr = self.source.latest
        img = fr.image if fr is not None and fr.index == est.frame_index and est.camera == "ok" else None
        # validation on this thread too: the detector's last detections belong to this frame
        val = self.validation.check(est.T_cam_ct, self.detector.last, est.image_points_px, self.K, self.dist)
        if est.camera == "ok":
            self._watch_colour_clash(self.detector.colour_share)
        with self._lock:
            self._last_image = (est, img, val)
            if est.camera == "ok":
                self._frames.append(float(est.t_capture))

    def _watch_colour_clash(self, share: float) -> None:
        """Raise / clear ``colour_clash`` from this frame's oversized ball-coloured share (0-1);
        on the stream thread (the alarm board and the event bus are thread-safe)."""
        if not self.running:
            return                        # stopping: the stop clears the setup conditions
        raised, run = self._clash
        if (share >= CLASH_SHARE) == raised:
            self._clash = (raised, 0)
            return
        run += 1
        if not raised and run >= CLASH_FRAMES:
            self._session.alert("warning", "colour_clash",
                                f"{100 * share:.0f} % of the image is the balls' colour but larger than a ball "
                                "(a drape or cover of their hue?): balls next to it can be lost; learn the ball "
                                "colour (click a ball)")
            self._clash = (True, 0)
            if not self.running:          # stopped meanwhile (its clear may have come first)
                self._session.clear_condition("colour_clash")
        elif raised and run >= CLASH_CLEAR_FRAMES:
            self._session.clear_condition("colour_clash")
            self._clash = (False, 0)
        else:
            self._clash = (raised, run)

    def start(self) -> None:
        self.stream.start()

    def stop(self) -> None:
        self.stream.stop()

    def capture(self, t: float):
        raise MonoTrackerError("a real camera runs on the real clock (clock='real')")

    def poll_frames(self) -> list[float]:
        with self._lock:
            out, self._frames = self._frames, []
        return out

    def latest_sample(self) -> PoseSample | None:
        est = self.stream.latest()
        if est is None:
            return None
        cached = self._sample_cache
        if cached is not None and cached[0] is est:
            return cached[1]  # the same estimate is the same sample (the loop handles each once)
        with self._lock:
            kept = self._last_image
        if kept is None or kept[0] is not est:
            # published but our subscriber (which pairs it with its image) has not run yet
            return None if cached is None else cached[1]
        smp = estimate_to_sample(est, self.fiducial_ids)
        smp.t_ready = float(est.t_published)
        smp.frame = kept[1]
        smp.validation = kept[2]
        self._sample_cache = (est, smp)
        return smp

    def latest_frame(self):
        fr, est = self.source.latest, self.stream.latest()
        return None if fr is None else (fr.image, fr.index, est)
