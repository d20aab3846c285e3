"""The simulated camera rigs of the digital twin (rows ``sim`` and ``sim-points`` of ``rigs/sources.py``).

* :class:`SimImageRig` (camera ``"sim"``): the rendered twin camera, vision's detector and registration.
* :class:`ProjectedFiducialRig` (camera ``"sim-points"``): the same twin at the level of detected
  points (exact ellipse centres + lens distortion + noise -> registration).

Both use the CT fiducials confirmed in the plan, take their truth (head pose over time, mm) from
the OR layout and the simulator's trajectories, and apply the simulated faults (``sim/faults.py``);
see :mod:`monotracker.engine.rigs.factory` for the whole picture.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from monotracker.engine.pipeline_priority import DEFAULT_POSE_NICE, normal_priority
from monotracker.engine.rigs.base import CameraRig, PoseSample, estimate_to_sample
from monotracker.engine.rigs.validation import KeepDetections, ValidationSet
from monotracker.geometry import apply_transform

log = logging.getLogger(__name__)

SIM_IMAGE_SIZE = (1280, 720)
SIM_FOCAL_PX = 1100.0
SIM_DIST = np.array([-0.06, 0.02, 0.0, 0.0, 0.0])
#: "sim-points" image noise of each ball centre (px, per axis): what the image detector achieves on
#: rendered and independently rendered frames (0.07-0.21 px, docs/vision.md); the rig's poses pass
#: the same per-frame trust rules as the image rigs' (at 0.3 px a third failed the TRE tail rule)
NOISE_PX = 0.15
#: exposure midpoint -> frame in memory for a 30 fps USB camera (half an exposure + readout +
#: transfer), our modelling choice; it is part of every measured capture -> command latency
SIM_TRANSPORT_DELAY_S = 0.030
DRAPE_BGR = (120, 95, 60)
SKIN_BGR = (140, 165, 205)


class _SimRig(CameraRig):
    """Shared by the simulated rigs: plan data, truth, faults, the real-clock thread."""

    def __init__(self, plan, trajectory: str, seed: int, fps: float, layout=None):
        super().__init__()
        from monotracker.sim.or_layout import default_layout

        self.layout = layout or default_layout()
        self.phantom = self.layout.phantom
        self.motion = self.layout.motion(trajectory, seed=seed + 1)
        self.rng = np.random.default_rng(seed)
        self.fps = float(fps)
        self.transport_delay_s = SIM_TRANSPORT_DELAY_S
        self.default_T_base_cam = self.layout.T_base_cam
        self.fiducials_ct = plan.registration_centres()
        self.fiducial_ids = [f.id for f in plan.registration_fiducials()]
        self.radius_mm = float(np.median([f.radius_mm for f in plan.registration_fiducials()]))
        self.validation = ValidationSet.from_plan(plan, self.radius_mm)
        self.target_ct = plan.target_lps_mm
        self.entry_ct = plan.entry_lps_mm
        self.occluded_ids: set[int] = set()  # phantom fiducial indices hidden (partial occlusion)
        self._last_frame = None
        self._last_sample: PoseSample | None = None
        self._index = 0
        self.clock = time.monotonic
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._new_frame_times: list[float] = []
        self._new_frame_info: list[tuple[float, int | None]] = []  # (t_capture, content digest)
        self._published: PoseSample | None = None
        self.last_error: str | None = None  # newest frame failure (camera thread), for diagnosis
        #: the pipeline thread's and camera process's nice value (``SessionConfig.pose_nice``,
        #: >= 0: normal or below the web server, :mod:`~monotracker.engine.pipeline_priority`) and
        #: what it runs at ("" until the thread started); ``on_priority(text)`` is told once
        self.nice = DEFAULT_POSE_NICE
        #: render the twin camera in its own process (real clock; ``SessionConfig.sim_camera_process``)
        self.camera_process = False
        self._camproc = None
        self.priority = ""
        self.on_priority = None
        #: the render runs inside the modelled transport delay (see :meth:`_run`)
        self.render_in_transport = True
        #: set whenever a new sample is published (the engine loop may wait on it)
        self.new_sample = threading.Event()

    def _frozen_frame(self, t: float):
        """camera-freeze as a real frozen camera shows it: the driver keeps delivering at the frame
        rate, newly stamped, but the content is the last frame, bit for bit (sensor noise never
        repeats a frame exactly)."""
        import dataclasses

        self._index += 1
        return dataclasses.replace(self._last_frame, t_capture=float(t), index=self._index)

    def frame_digest(self, frame) -> int | None:
        """A checksum of the frame's content (CRC-32 of the image, or of the image points): equal
        for consecutive frames only when the camera repeats a frame bit for bit."""
        import zlib

        if isinstance(frame, _ImageFrame):
            return zlib.crc32(np.ascontiguousarray(frame.image).data)
        if isinstance(frame, SimFrame):
            return zlib.crc32(np.ascontiguousarray(frame.points_px).tobytes()
                              + np.ascontiguousarray(frame.point_ids).tobytes())
        return None

    def poll_frame_info(self) -> list[tuple[float, int | None]]:
        with self._lock:
            out, self._new_frame_info = self._new_frame_info, []
            self._new_frame_times = []
        return out

    # truth
    def truth_T_cam_ct(self, t: float) -> np.ndarray:
        return self.layout.T_cam_ct(self.motion, t)

    def truth_T_base_ct(self, t: float) -> np.ndarray:
        return self.layout.T_base_ct(self.motion, t)

    def _finish(self, smp: PoseSample, truth_T: np.ndarray) -> PoseSample:
        """Apply the bad-pose fault and fill the truth fields."""
        if smp.ok and smp.T_cam_ct is not None and self.fault == "bad-pose":
            from monotracker.sim.faults import corrupt_pose

            smp.T_cam_ct = corrupt_pose(smp.T_cam_ct, self.rng, self.entry_ct)
        smp.truth_T_cam_ct = truth_T
        if smp.T_cam_ct is not None and self.target_ct is not None:
            smp.truth_tre_mm = float(np.linalg.norm(apply_transform(smp.T_cam_ct, self.target_ct)
                                                    - apply_transform(truth_T, self.target_ct)))
        self._last_sample = smp
        return smp

    # real clock: capture + estimate on our own thread at the camera rate
    def start(self) -> None:
        if self._thread is not None:
            return
        self._camproc = self._start_camera_process() if self.camera_process else None
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="monotracker-simcam", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        th = self._thread
        if th is not None:
            th.join(2.0)
        self._thread = None
        camproc, self._camproc = self._camproc, None
        if camproc is not None:
            camproc.close()

    def _start_camera_process(self):
        """The rig's camera rendering in its own process (``engine/rigs/sim_camera_process.py``), or None
        (this rig renders nothing worth a process, or the process could not start: then the
        render stays on the pipeline thread, and the log says why)."""
        return None

    def _run(self) -> None:
        """The simulated camera + pose pipeline thread: one frame per camera period, always the
        newest (a late thread drops frames rather than queueing them), at normal priority, never
        above the web server and the STOP path (:mod:`~monotracker.engine.pipeline_priority`).

        The render is the simulated camera's hardware at work: with ``render_in_transport``
        (default) it runs inside the frame's modelled transport delay, as a real camera's
        readout and USB transfer do: a frame exposed at ``t`` is rendered from ``t`` on and
        handed over at ``t + transport_delay_s`` at the earliest (never sooner than a real
        camera would deliver it; later when the render overruns, and that lateness is pose
        age). Without it (the baseline) the render starts ``transport_delay_s`` after the
        exposure it shows, so its time adds to the pose age."""
        self.priority = normal_priority(self.nice)
        if self._camproc is not None:
            self.priority += f"; camera process pid {self._camproc.pid}: {self._camproc.priority}"
        log.info("simulated camera pipeline thread: %s", self.priority)
        if self.on_priority is not None:
            try:
                self.on_priority(self.priority)
            except Exception:  # a report must never stop the camera
                log.exception("reporting the pipeline priority failed")
        period = 1.0 / self.fps
        t_next = self.clock()
        last_t = last_digest = None
        render_s = 0.0  # running estimate of the render's wall time (s)
        camproc = self._camproc
        while not self._stop.is_set():
            try:
                if camproc is not None:  # the twin camera renders in its own process
                    got = self._receive(camproc, 0.05)
                    if got is None:
                        if not camproc.alive():
                            self.last_error = "simulated camera process ended"
                            self._stop.wait(0.05)
                        continue
                    frame, w_render = got
                    late_s, w1 = 0.0, self.clock()
                    w0, c0 = w1 - w_render, 0.0
                    c1 = 0.0
                else:
                    now = self.clock()
                    if now < t_next:
                        self._stop.wait(t_next - now)
                        continue
                    late_s = now - t_next
                    t_next = max(t_next + period, now)  # drop frames rather than queue them
                    d = self.transport_delay_s
                    ahead = min(render_s, d) if self.render_in_transport else 0.0
                    t_exp = now - d + ahead  # the exposure this frame shows
                    w0, c0 = self.clock(), time.thread_time()
                    frame = self.capture(t_exp)
                    w1, c1 = self.clock(), time.thread_time()
                    if self.render_in_transport:
                        render_s = w1 - w0 if render_s == 0.0 else 0.8 * render_s + 0.2 * (w1 - w0)
                        hold = frame.t_capture + d - w1
                        if hold > 0:  # rendered faster than the camera delivers: wait for the hand-over
                            if self._stop.wait(hold):
                                break
                w_arrived = self.clock()
                if frame.t_capture == last_t:
                    continue  # frozen: nothing new
                last_t = frame.t_capture
                digest = self.frame_digest(frame)
                with self._lock:
                    self._new_frame_times.append(frame.t_capture)
                    self._new_frame_info.append((frame.t_capture, digest))
                if digest is not None and digest == last_digest:
                    continue  # a bit-identical repeat: never estimated (a stale pose, newly stamped)
                last_digest = digest
                c2 = time.thread_time()
                smp = self.estimate(frame)
                w3, c3 = self.clock(), time.thread_time()
            except Exception as exc:  # the camera thread must outlive a bad frame
                # No frame is published, so the engine's freeze watchdog holds the arm; the
                # thread keeps capturing so that the camera comes back by itself.
                log.exception("simulated camera: frame failed")
                self.last_error = f"{type(exc).__name__}: {exc}"
                continue
            raw = smp.raw
            smp.stages = {**smp.stages, "late_s": late_s, "render_s": w1 - w0, "render_cpu_s": c1 - c0,
                          "arrived_s": w_arrived - frame.t_capture, "estimate_s": w3 - w_arrived,
                          "estimate_cpu_s": c3 - c2, "detect_s": float(getattr(raw, "detect_s", np.nan)),
                          "register_s": float(getattr(raw, "register_s", np.nan))}
            smp.t_ready = self.clock()
            with self._lock:
                self._published = smp
            self.new_sample.set()
            self.after_publish()   # a due frame's camera-motion check, now that its pose is out

    def _receive(self, camproc, timeout_s: float):
        raise NotImplementedError  # only rigs that render in a camera process

    def poll_frames(self) -> list[float]:
        with self._lock:
            out, self._new_frame_times = self._new_frame_times, []
        return out

    def latest_sample(self) -> PoseSample | None:
        with self._lock:
            return self._published


# ====================================================================== rendered images
@dataclass
class _ImageFrame:
    image: np.ndarray
    t_capture: float
    index: int
    truth: object


class SimImageRig(_SimRig):
    """camera="sim": vision's SimulatedCamera + PoseTracker (see the module docstring)."""

    def __init__(self, plan, trajectory: str = "breathing", seed: int = 0, fps: float = 30.0, layout=None,
                 optics=None, rules=None):
        """``rules``: the per-frame trust rules (vision's ``TrackerConfig``, ``SessionConfig.frame_rules``)."""
        super().__init__(plan, trajectory, seed, fps, layout)
        from monotracker.sim.camera_sim import SimulatedCamera
        from monotracker.vision.pose_stream import PoseTracker

        # the camera stands where the OR layout puts it (vision's default is straight above the patch)
        # optics: None = the simple render (cheap enough for 30 fps on 2 cores); a preset name of
        # sim.optics.PRESETS ("photo", "degraded") = photo-like frames (~40 ms more per frame)
        self._cam_kwargs = dict(trajectory=self.motion, fps=fps, seed=seed, T_cam_world=self.layout.T_cam_ct0,
                                optics=optics)
        self.cam = SimulatedCamera(**self._cam_kwargs)
        self._pending_motion: str | None = None   # a camera-motion fault to start at the next frame
        self.camera_model = self.cam.camera
        self.K = self.camera_model.K
        self.dist = self.camera_model.dist
        self.image_size = tuple(self.camera_model.image_size)
        self.detector = KeepDetections(self.K, self.radius_mm)
        self.tracker = PoseTracker(self.fiducials_ct, self.camera_model, detector=self.detector,
                                   radius_mm=self.radius_mm, target_ct=self.target_ct, config=rules,
                                   watch_ct=self.validation.centres_ct)   # validation balls searched too

    #: the camera-motion faults (``camera-bump``, ``camera-sag``) move this rig's rendered camera
    renders_camera_motion = True
    #: its frames show a static background: the factory gives its tracker a camera-motion watch
    watches_background = True

    def set_fault(self, name: str) -> None:
        """Apply fault ``name``; a camera-motion fault moves the twin camera in the room from the
        next frame on (from the session time of that frame: ``sim/faults.py``'s CameraMotion),
        "none" puts it back where the hand-eye was calibrated."""
        from monotracker.sim.faults import CAMERA_MOTION_FAULTS

        super().set_fault(name)
        moving = name if name in CAMERA_MOTION_FAULTS else None
        if moving is None:
            self.cam.camera_motion = None
        self._pending_motion = moving
        camproc = self._camproc
        if camproc is not None:
            camproc.set_camera_motion(moving)

    def capture(self, t: float) -> _ImageFrame:
        if self.fault == "camera-freeze" and self._last_frame is not None:
            return self._frozen_frame(t)
        pending, self._pending_motion = getattr(self, "_pending_motion", None), None
        if pending is not None:
            from monotracker.sim.faults import CameraMotion

            self.cam.camera_motion = CameraMotion(pending, float(t))
        img, truth = self.cam.render(t)
        return self._new_frame(img, t, truth)

    def _receive(self, camproc, timeout_s: float):
        """The newest frame from the camera process with the faults applied, and its render
        time (s); None when none came within ``timeout_s``."""
        got = camproc.next_frame(timeout_s)
        if got is None:
            return None
        img, _index, t, truth, render_s = got
        if self.fault == "camera-freeze" and self._last_frame is not None:
            return self._frozen_frame(t), render_s
        return self._new_frame(img, t, truth), render_s

    def _start_camera_process(self):
        from monotracker.engine.rigs.sim_camera_process import SimCameraProcess

        proc = SimCameraProcess(self._cam_kwargs, self.image_size, self.fps, self.transport_delay_s, self.nice)
        try:
            proc.start()
        except Exception as exc:  # noqa: BLE001 - the in-thread render still works, more slowly
            log.warning("simulated camera process not started (%s: %s); rendering on the pose thread",
                        type(exc).__name__, exc)
            proc.close()
            return None
        return proc

    def _new_frame(self, img: np.ndarray, t: float, truth) -> "_ImageFrame":
        """A rendered image becomes the newest frame, with the injected occlusions drawn on it."""
        import cv2

        centres = np.asarray(truth.ellipse_centres_px, float)
        radii = np.asarray(truth.radius_px, float)
        if self.fault == "occlude-all":
            # a drape pulled over the whole fiducial patch
            ok = np.all(np.isfinite(centres), axis=1)
            if ok.any():
                r = 2.5 * float(np.nanmax(radii))
                pts = np.concatenate([centres[ok] + r * np.array([np.cos(a), np.sin(a)])
                                      for a in np.linspace(0, 2 * np.pi, 16, endpoint=False)])
                hull = cv2.convexHull(np.round(pts).astype(np.int32))
                cv2.fillConvexPoly(img, hull, DRAPE_BGR, cv2.LINE_AA)
        for i in tuple(self.occluded_ids):  # another thread may swap the set
            if np.all(np.isfinite(centres[i])):
                c = tuple(int(round(v)) for v in centres[i])
                cv2.circle(img, c, int(np.ceil(1.6 * radii[i])) + 2, SKIN_BGR, -1, cv2.LINE_AA)
        self._index += 1
        self._last_frame = _ImageFrame(img, float(t), self._index, truth)
        return self._last_frame

    def estimate(self, frame: _ImageFrame) -> PoseSample:
        from monotracker.vision.frames import Frame

        est = self.tracker.process(Frame(frame.image, frame.t_capture, frame.index, frame.truth))
        smp = self._finish(estimate_to_sample(est, self.fiducial_ids), np.asarray(frame.truth.T_cam_ct, float))
        smp.frame = frame.image
        smp.validation = self.validation.check(smp.T_cam_ct, self.detector.last, est.image_points_px, self.K,
                                               self.dist)
        return smp

    def latest_frame(self):
        fr, smp = self._last_frame, self._last_sample
        if fr is None:
            return None
        return fr.image, fr.index, None if smp is None else smp.raw


# ====================================================================== projected points
@dataclass
class SimFrame:
    """A point-level frame: capture time, index, true pose, image points (px, shuffled), their
    phantom fiducial indices and the balls' minor semi-axes (px; None: unknown, e.g. replayed)."""

    t_capture: float
    index: int
    truth_T_cam_ct: np.ndarray
    points_px: np.ndarray
    point_ids: np.ndarray
    minor_px: np.ndarray | None = None


class ProjectedFiducialRig(_SimRig):
    """camera="sim-points": see the module docstring. The points go through vision's
    ``PoseTracker`` (a :class:`~monotracker.vision.point_detector.PointDetector` hands it the
    points), so this rig applies the same per-frame trust rules as the image rigs (``rules``:
    vision's ``TrackerConfig`` from ``SessionConfig.frame_rules``)."""

    def __init__(self, plan, trajectory: str = "breathing", seed: int = 0, noise_px: float = NOISE_PX,
                 fps: float = 30.0, layout=None, rules=None):
        super().__init__(plan, trajectory, seed, fps, layout)
        self.rules = rules
        self.tracker = None  # built at the first estimate (a replay sets the scene first)
        self.detector = None
        from monotracker.sim.scenes import default_K

        self.noise_px = float(noise_px)
        self.K = default_K(SIM_FOCAL_PX, SIM_IMAGE_SIZE)
        self.dist = SIM_DIST.copy()
        self.image_size = SIM_IMAGE_SIZE
        self.true_fiducials_ct = self.phantom.fiducial_centres_lps  # truth (the phantom), computed once
        self._blank = None
        from monotracker.registration import pnp_kernels

        pnp_kernels.warm_up()   # the tracker comes at the first frame; its compiled fit is loaded now

    def _make_tracker(self) -> None:
        from monotracker.vision.camera_model import CameraModel
        from monotracker.vision.point_detector import PointDetector
        from monotracker.vision.pose_tracker import PoseTracker

        model = CameraModel(np.asarray(self.K, float), np.asarray(self.dist, float).ravel(), tuple(self.image_size))
        self.detector = PointDetector()
        self.tracker = PoseTracker(self.fiducials_ct, model, detector=self.detector, radius_mm=self.radius_mm,
                                   target_ct=self.target_ct, config=self.rules)
        w, h = self.image_size
        self._blank = np.zeros((int(h), int(w), 3), np.uint8)  # the frame size the tracker checks; never drawn on

    def capture(self, t: float) -> SimFrame:
        from monotracker.registration.projection import distort_normalised, normalised_to_pixels
        from monotracker.sim.scenes import ellipse_centre_normalised

        if self.fault == "camera-freeze" and self._last_frame is not None:
            return self._frozen_frame(t)
        T = self.truth_T_cam_ct(t)
        Xc = apply_transform(T, self.true_fiducials_ct)
        ids = np.arange(len(Xc))
        keep = Xc[:, 2] > 50.0
        if self.fault == "occlude-all":
            keep[:] = False
        for i in tuple(self.occluded_ids):  # another thread may swap the set
            keep[i] = False
        r = self.phantom.fiducial_radius_mm
        xy = ellipse_centre_normalised(Xc[keep], r) if keep.any() else np.zeros((0, 2))
        px = normalised_to_pixels(distort_normalised(xy, self.dist), self.K)
        px = px + self.rng.normal(scale=self.noise_px, size=px.shape)
        z = Xc[keep, 2]
        minor = float(self.K[0, 0]) * r / np.sqrt(np.maximum(z ** 2 - r ** 2, 1e-9))  # ball image size, px
        ids = ids[keep]
        w, h = self.image_size
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        px, ids, minor = px[inside], ids[inside], minor[inside]
        order = self.rng.permutation(len(px))
        self._index += 1
        self._last_frame = SimFrame(float(t), self._index, T, px[order], ids[order], minor[order])
        return self._last_frame

    def estimate(self, frame: SimFrame) -> PoseSample:
        from monotracker.vision.frames import Frame

        if self.tracker is None:
            self._make_tracker()
        pts = np.asarray(frame.points_px, float).reshape(-1, 2)
        minor = np.full(len(pts), np.nan) if frame.minor_px is None else np.asarray(frame.minor_px, float)
        self.detector.set(pts, minor)
        est = self.tracker.process(Frame(self._blank, frame.t_capture, frame.index))
        smp = estimate_to_sample(est, self.fiducial_ids)
        smp.frame = frame
        smp.validation = self.validation.check(smp.T_cam_ct, pts, est.image_points_px, self.K, self.dist)
        return self._finish(smp, frame.truth_T_cam_ct)

    def latest_frame(self):
        """A schematic image (grey, the detected points as green discs) for the overlay."""
        import cv2

        fr, smp = self._last_frame, self._last_sample
        if fr is None:
            return None
        w, h = self.image_size
        img = np.full((h, w, 3), 60, np.uint8)
        for p in fr.points_px:
            cv2.circle(img, (int(round(p[0])), int(round(p[1]))), 9, (60, 200, 60), -1, cv2.LINE_AA)
        return img, fr.index, smp
