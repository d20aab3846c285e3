"""Camera rigs: frames -> fiducials in the image -> registration -> :class:`PoseSample`.

Three rigs, chosen by the camera source:

* ``"sim"`` -- :class:`SimImageRig`, the digital-twin camera: vision's ``SimulatedCamera`` renders
  the phantom (exact ray-sphere fiducials, skin, blur, noise) at the session time, placed where
  the OR layout puts the camera (``monotracker.sim.or_layout``); vision's ``PoseTracker``
  detects the balls and registers them (``registration.register`` with the previous pose as
  prior). A frame reaches the software ``transport_delay_s`` (30 ms) after exposure.
* ``"sim-points"`` -- :class:`ProjectedFiducialRig`, the same twin at the level of detected
  points (no rendering, no image detector): exact ellipse centres of the balls + lens distortion
  + 0.3 px noise -> registration. Cheaper; for studies of the loop itself.
* ``"device:N" | "file:PATH" | "folder:PATH"`` -- :class:`StreamRig`: vision's ``PoseStream`` on
  a real frame source (its own thread; clock="real" only), with the calibration file given to
  ``set_camera`` (``CameraModel.load``) or, without one, vision's default model and a warning.
* ``"replay:DIR"`` -- :class:`StreamRig` on a session recording (``vision.replay_source``), paced
  at the recorded frame times, with the recording's own calibration unless one is given.

Both simulated rigs use the CT fiducials *confirmed in the plan* (from the CT detector), not the
phantom's true centres, so CT detection error is part of the measured TRE; their truth (head
pose over time) comes from the OR layout and vision's trajectories. Faults (``sim/faults.py``)
are applied to the simulated hardware here.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from monotracker.engine.components import CameraRig, PoseSample
from monotracker.engine.verification import KeepDetections, ValidationSet
from monotracker.errors import MonoTrackerError
from monotracker.geometry import apply_transform

log = logging.getLogger(__name__)

SIM_IMAGE_SIZE = (1280, 720)
SIM_FOCAL_PX = 1100.0
SIM_DIST = np.array([-0.06, 0.02, 0.0, 0.0, 0.0])
#: exposure midpoint -> frame in memory for a 30 fps USB camera (half an exposure + readout +
#: transfer), our modelling choice; it is part of every measured capture -> command latency
SIM_TRANSPORT_DELAY_S = 0.030
DRAPE_BGR = (120, 95, 60)
SKIN_BGR = (140, 165, 205)


def _nan_to_none(v) -> float | None:
    return None if v is None or not np.isfinite(v) else float(v)


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
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="monotracker-simcam", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        th = self._thread
        if th is not None:
            th.join(2.0)
        self._thread = None

    def _run(self) -> None:
        period = 1.0 / self.fps
        t_next = self.clock()
        last_t = last_digest = None
        while not self._stop.is_set():
            now = self.clock()
            if now < t_next:
                self._stop.wait(t_next - now)
                continue
            t_next = max(t_next + period, now)  # drop frames rather than queue them
            try:
                frame = self.capture(now - self.transport_delay_s)  # exposed d seconds ago
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
                smp = self.estimate(frame)
            except Exception as exc:  # noqa: BLE001 - the camera thread must outlive a bad frame
                # No frame is published, so the engine's freeze watchdog holds the arm; the
                # thread keeps capturing so that the camera comes back by itself.
                log.exception("simulated camera: frame failed")
                self.last_error = f"{type(exc).__name__}: {exc}"
                continue
            smp.t_ready = self.clock()
            with self._lock:
                self._published = smp

    def poll_frames(self) -> list[float]:
        with self._lock:
            out, self._new_frame_times = self._new_frame_times, []
        return out

    def latest_sample(self) -> PoseSample | None:
        with self._lock:
            return self._published

    def set_ball_colour(self, colour) -> str:
        """Detect balls of ``colour`` (vision's BallColour) from the next frame on; '' or why not."""
        det = getattr(getattr(self, "tracker", None), "detector", None)
        if det is None or not hasattr(det, "set_colour"):
            return "this camera source has no colour detector (sim-points works on points)"
        det.set_colour(colour)
        return ""


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
                 optics=None):
        super().__init__(plan, trajectory, seed, fps, layout)
        from monotracker.sim.camera_sim import SimulatedCamera
        from monotracker.vision.pose_stream import PoseTracker

        # the camera stands where the OR layout puts it (vision's default is straight above the patch)
        # optics: None = the simple render (cheap enough for 30 fps on 2 cores); a preset name of
        # sim.optics.PRESETS ("photo", "degraded") = photo-like frames (~40 ms more per frame)
        self.cam = SimulatedCamera(trajectory=self.motion, fps=fps, seed=seed, T_cam_world=self.layout.T_cam_ct0,
                                   optics=optics)
        self.camera_model = self.cam.camera
        self.K = self.camera_model.K
        self.dist = self.camera_model.dist
        self.image_size = tuple(self.camera_model.image_size)
        self.detector = KeepDetections(self.K, self.radius_mm)
        self.tracker = PoseTracker(self.fiducials_ct, self.camera_model, detector=self.detector,
                                   radius_mm=self.radius_mm, target_ct=self.target_ct)

    def capture(self, t: float) -> _ImageFrame:
        import cv2

        if self.fault == "camera-freeze" and self._last_frame is not None:
            return self._frozen_frame(t)
        img, truth = self.cam.render(t)
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


def estimate_to_sample(est, fiducial_ids: list[int]) -> PoseSample:
    """vision's PoseEstimate -> PoseSample (statuses and residuals keyed by plan fiducial id)."""
    status = {fiducial_ids[j]: s for j, s in enumerate(est.status) if j < len(fiducial_ids)}
    res = {fiducial_ids[j]: float(r) for j, r in enumerate(np.asarray(est.residuals_px, float))
           if j < len(fiducial_ids) and np.isfinite(r)}
    reason = est.reason or "ok"
    return PoseSample(
        t_capture=float(est.t_capture), frame_index=int(est.frame_index), ok=bool(est.ok), reason=reason,
        T_cam_ct=None if est.T_cam_ct is None else np.array(est.T_cam_ct, float), n_matched=int(est.n_matched),
        fiducial_status=status, residuals_px=res, fre_mm=_nan_to_none(est.fre_mm),
        predicted_tre_mm=_nan_to_none(est.predicted_tre_mm), raw=est, code=getattr(est, "code", ""),
        moved={fiducial_ids[j]: float(mm) for j, mm in getattr(est, "moved", []) if j < len(fiducial_ids)})


# ====================================================================== projected points
@dataclass
class SimFrame:
    """A point-level frame: capture time, index, true pose, image points (px, shuffled)."""

    t_capture: float
    index: int
    truth_T_cam_ct: np.ndarray
    points_px: np.ndarray
    point_ids: np.ndarray


class ProjectedFiducialRig(_SimRig):
    """camera="sim-points": see the module docstring."""

    def __init__(self, plan, trajectory: str = "breathing", seed: int = 0, noise_px: float = 0.3,
                 fps: float = 30.0, layout=None):
        super().__init__(plan, trajectory, seed, fps, layout)
        from monotracker.sim.scenes import default_K

        self.noise_px = float(noise_px)
        self.K = default_K(SIM_FOCAL_PX, SIM_IMAGE_SIZE)
        self.dist = SIM_DIST.copy()
        self.image_size = SIM_IMAGE_SIZE
        self.true_fiducials_ct = self.phantom.fiducial_centres_lps  # truth (the phantom), computed once
        self._prior: np.ndarray | None = None

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
        xy = ellipse_centre_normalised(Xc[keep], self.phantom.fiducial_radius_mm) if keep.any() else np.zeros((0, 2))
        px = normalised_to_pixels(distort_normalised(xy, self.dist), self.K)
        px = px + self.rng.normal(scale=self.noise_px, size=px.shape)
        ids = ids[keep]
        w, h = self.image_size
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        px, ids = px[inside], ids[inside]
        order = self.rng.permutation(len(px))
        self._index += 1
        self._last_frame = SimFrame(float(t), self._index, T, px[order], ids[order])
        return self._last_frame

    def estimate(self, frame: SimFrame) -> PoseSample:
        from monotracker.registration import register

        n_pts = len(frame.points_px)
        if n_pts < 4:
            self._prior = None
            smp = PoseSample(frame.t_capture, frame.index, False, f"{n_pts} fiducials visible (need 4)", None, n_pts,
                             fiducial_status={fid: "occluded" for fid in self.fiducial_ids}, frame=frame)
            return self._finish(smp, frame.truth_T_cam_ct)
        reg = register(self.fiducials_ct, frame.points_px, self.K, self.dist, radius_mm=self.radius_mm,
                       method="robust", prior=self._prior)
        self._prior = reg.T_cam_ct if reg.ok else None
        status = {fid: "occluded" for fid in self.fiducial_ids}
        residuals = {}
        if reg.ok:
            for (_ii, fi), r in zip(reg.pairs, reg.residuals_px):
                status[self.fiducial_ids[int(fi)]] = "seen"
                residuals[self.fiducial_ids[int(fi)]] = float(r)
        pred = float(reg.predicted_tre_mm(self.target_ct)) if reg.ok and self.target_ct is not None else None
        smp = PoseSample(
            t_capture=frame.t_capture, frame_index=frame.index, ok=bool(reg.ok), reason=reg.reason or "ok",
            T_cam_ct=reg.T_cam_ct if reg.ok else None, n_matched=len(reg.pairs) if reg.ok else 0,
            fiducial_status=status, residuals_px=residuals, fre_mm=float(reg.fre_mm) if reg.ok else None,
            predicted_tre_mm=pred, raw=reg, frame=frame,
        )
        if reg.ok:
            used = frame.points_px[[int(ii) for ii, _fi in reg.pairs]]
            smp.validation = self.validation.check(reg.T_cam_ct, frame.points_px, used, self.K, self.dist)
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


# ====================================================================== real cameras
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

    def __init__(self, source: str, calibration_path: str | None, plan, session, camera_adapt: str = "",
                 max_predicted_tre_mm: float | None = None):
        super().__init__()
        from monotracker.vision.camera_model import CameraModel, default_camera
        from monotracker.vision.frames import open_source
        from monotracker.vision.pose_stream import PoseStream, PoseTracker

        kind, _, arg = source.partition(":")
        if kind == "device" and not arg.isdigit():
            raise MonoTrackerError(f"camera device must be a number, as in device:0 (got {source!r})")
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
        self.validation = ValidationSet.from_plan(plan, radius)
        try:
            src = replay if kind == "replay" else open_source(int(arg) if kind == "device" else arg)
        except MonoTrackerError:
            raise
        except Exception as exc:  # noqa: BLE001 - a camera that will not open is an operator problem
            raise MonoTrackerError(f"cannot open camera {source}: {exc}") from exc
        self.detector = KeepDetections(model.K, radius)  # keeps the blobs for the validation fiducials
        tracker = PoseTracker(plan.registration_centres(), model, detector=self.detector, radius_mm=radius,
                              target_ct=plan.target_lps_mm)
        if max_predicted_tre_mm is not None:
            tracker.config.max_predicted_tre_mm = float(max_predicted_tre_mm)
        if model.ball_colour is not None:
            self.detector.set_colour(model.ball_colour)      # learned earlier, saved with the calibration
        self.tracker = tracker
        self.source = _KeepLatest(src)
        self.stream = PoseStream(source=self.source, tracker=tracker)
        self._lock = threading.Lock()
        self._frames: list[float] = []
        self._last_image = None
        self._sample_cache = None
        self.stream.subscribe(self._on_estimate)

    def _on_estimate(self, est) -> None:
        # runs on the stream thread right after the frame was processed: the newest frame read is
        # the one this estimate came from (kept with it for session recording)
        fr = self.source.latest
        img = fr.image if fr is not None and fr.index == est.frame_index and est.camera == "ok" else None
        # validation on this thread too: the detector's last detections belong to this frame
        val = self.validation.check(est.T_cam_ct, self.detector.last, est.image_points_px, self.K, self.dist)
        with self._lock:
            self._last_image = (est, img, val)
            if est.camera == "ok":
                self._frames.append(float(est.t_capture))

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

    set_ball_colour = _SimRig.set_ball_colour


def make_vision_rig(source, calibration_path, plan, cfg, session) -> CameraRig:
    if source in ("sim", "sim-points"):
        if source == "sim":
            rig = SimImageRig(plan, trajectory=cfg.trajectory, seed=cfg.seed, fps=cfg.camera_fps,
                              optics=getattr(cfg, "camera_optics", None))
        else:
            rig = ProjectedFiducialRig(plan, trajectory=cfg.trajectory, seed=cfg.seed, fps=cfg.camera_fps)
        rig.clock = session.clock
        if getattr(rig, "tracker", None) is not None:
            rig.tracker.config.max_predicted_tre_mm = float(cfg.max_predicted_tre_mm)
    else:
        if cfg.clock != "real":
            raise MonoTrackerError("real cameras need a real-clock session (clock='real')")
        rig = StreamRig(source, calibration_path, plan, session, camera_adapt=cfg.camera_adapt,
                        max_predicted_tre_mm=cfg.max_predicted_tre_mm)
    rig.validation.limit_mm = float(cfg.max_validation_tre_mm)
    return rig
