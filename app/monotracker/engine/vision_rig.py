"""Camera rigs: frames -> fiducial image points -> ``registration.register`` -> PoseSample.

:class:`ProjectedFiducialRig` (camera="sim" until the vision package's image pipeline is wired):
the digital-twin camera at the level of *detected points*. For each frame it takes the head's
true pose (``monotracker.sim.or_layout`` + head motion), computes the exact centre of each
fiducial sphere's image ellipse (``sim.scenes.ellipse_centre_normalised``: the sphere-centre bias
is in the data, the registration must correct it), applies lens distortion, adds Gaussian pixel
noise (``noise_px``, 0.3 px: a good sub-pixel detector), drops fiducials that are occluded or
outside the image, shuffles the points and runs the real registration
(``monotracker.registration.register``, robust method, previous pose as prior). It does not
render images or run an image detector; its ``latest_frame()`` draws a schematic image (grey
background, the fiducial ellipses in green) for the overlay. A frame reaches the software
``transport_delay_s`` (30 ms) after it was exposed, as with a USB camera.

The registration uses the CT fiducials *confirmed in the plan* (from the CT detector), not the
phantom's true centres, so CT detection error is part of the measured TRE.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from monotracker.engine.components import CameraRig, PoseSample
from monotracker.errors import MonoTrackerError
from monotracker.geometry import apply_transform

SIM_IMAGE_SIZE = (1280, 720)
SIM_FOCAL_PX = 1100.0
SIM_DIST = np.array([-0.06, 0.02, 0.0, 0.0, 0.0])
#: exposure midpoint -> frame in memory for a 30 fps USB camera (half an exposure + readout +
#: transfer), our modelling choice; it is part of every measured capture -> command latency
SIM_TRANSPORT_DELAY_S = 0.030


@dataclass
class SimFrame:
    """A simulated frame: capture time (session clock s), index, true pose, image points (px,
    shuffled), and for each point the true fiducial id (phantom numbering) or -1."""

    t_capture: float
    index: int
    truth_T_cam_ct: np.ndarray
    points_px: np.ndarray
    point_ids: np.ndarray


class ProjectedFiducialRig(CameraRig):
    """See the module docstring. ``plan``: the session plan (confirmed fiducials, entry/target)."""

    def __init__(self, plan, trajectory: str = "breathing", seed: int = 0, noise_px: float = 0.3,
                 fps: float = 30.0, layout=None):
        super().__init__()
        from monotracker.sim.or_layout import default_layout
        from monotracker.sim.scenes import default_K

        self.layout = layout or default_layout()
        self.phantom = self.layout.phantom
        self.true_fiducials_ct = self.phantom.fiducial_centres_lps  # truth (the phantom), computed once
        self.motion = self.layout.motion(trajectory, seed)
        self.rng = np.random.default_rng(seed)
        self.noise_px = float(noise_px)
        self.fps = float(fps)
        self.K = default_K(SIM_FOCAL_PX, SIM_IMAGE_SIZE)
        self.dist = SIM_DIST.copy()
        self.image_size = SIM_IMAGE_SIZE
        self.transport_delay_s = SIM_TRANSPORT_DELAY_S
        self.default_T_base_cam = self.layout.T_base_cam
        self.true_T_base_cam = self.layout.T_base_cam
        self.fiducials_ct = plan.fiducial_centres()
        self.fiducial_ids = [f.id for f in plan.usable_fiducials()]
        self.radius_mm = float(np.median([f.radius_mm for f in plan.usable_fiducials()]))
        self.target_ct = plan.target_lps_mm
        self.entry_ct = plan.entry_lps_mm
        self.occluded_ids: set[int] = set()
        self._index = 0
        self._last_frame: SimFrame | None = None
        self._prior: np.ndarray | None = None
        self._last_sample: PoseSample | None = None
        # real-clock thread state
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._new_frame_times: list[float] = []
        self.clock = time.monotonic

    # ------------------------------------------------------------------ truth
    def truth_T_cam_ct(self, t: float) -> np.ndarray:
        return self.layout.T_cam_ct(self.motion, t)

    def truth_T_base_ct(self, t: float) -> np.ndarray:
        return self.layout.T_base_ct(self.motion, t)

    # ------------------------------------------------------------------ frames
    def capture(self, t: float) -> SimFrame:
        from monotracker.registration.projection import distort_normalised, normalised_to_pixels
        from monotracker.sim.scenes import ellipse_centre_normalised

        if self.fault == "camera-freeze" and self._last_frame is not None:
            return self._last_frame
        T = self.truth_T_cam_ct(t)
        Xc = apply_transform(T, self.true_fiducials_ct)
        ids = np.arange(len(Xc))
        keep = Xc[:, 2] > 50.0
        if self.fault == "occlude-all":
            keep[:] = False
        for i in self.occluded_ids:
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
            s = PoseSample(frame.t_capture, frame.index, False, f"{n_pts} fiducials visible (need 4)", None, n_pts,
                           fiducial_status=self._status(frame, None), truth_T_cam_ct=frame.truth_T_cam_ct)
            self._last_sample = s
            return s
        reg = register(self.fiducials_ct, frame.points_px, self.K, self.dist, radius_mm=self.radius_mm,
                       method="robust", prior=self._prior)
        T = reg.T_cam_ct if reg.ok else None
        self._prior = T
        if reg.ok and self.fault == "bad-pose":
            from monotracker.sim.faults import corrupt_pose

            T = corrupt_pose(T, self.rng, self.entry_ct)
        tre = None
        if T is not None and self.target_ct is not None:
            tre = float(np.linalg.norm(apply_transform(T, self.target_ct)
                                       - apply_transform(frame.truth_T_cam_ct, self.target_ct)))
        pred = None
        if reg.ok and self.target_ct is not None:
            pred = float(reg.predicted_tre_mm(self.target_ct))
        residuals = {}
        if reg.ok:
            residuals = {self.fiducial_ids[int(fi)]: float(r) for (_ii, fi), r in zip(reg.pairs, reg.residuals_px)}
        s = PoseSample(
            t_capture=frame.t_capture, frame_index=frame.index, ok=bool(reg.ok), reason=reg.reason or "ok",
            T_cam_ct=T, n_matched=len(reg.pairs) if reg.ok else 0,
            fiducial_status=self._status(frame, reg if reg.ok else None), residuals_px=residuals,
            fre_mm=float(reg.fre_mm) if reg.ok else None, predicted_tre_mm=pred,
            truth_T_cam_ct=frame.truth_T_cam_ct, truth_tre_mm=tre, raw=reg,
        )
        self._last_sample = s
        return s

    def _status(self, frame: SimFrame, reg) -> dict:
        """Plan fiducial id -> "visible" (matched in this frame) | "occluded" (not matched)."""
        out = {fid: "occluded" for fid in self.fiducial_ids}
        if reg is not None:
            for _ii, fi in reg.pairs:
                out[self.fiducial_ids[int(fi)]] = "visible"
        return out

    # ------------------------------------------------------------------ overlay image
    def latest_frame(self):
        import cv2

        fr, smp = self._last_frame, self._last_sample
        if fr is None:
            return None
        w, h = self.image_size
        img = np.full((h, w, 3), 60, np.uint8)
        for p in fr.points_px:
            cv2.circle(img, (int(round(p[0])), int(round(p[1]))), 9, (60, 200, 60), -1, cv2.LINE_AA)
        return img, fr.index, smp

    # ------------------------------------------------------------------ real clock
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
        last_t = None
        while not self._stop.is_set():
            now = self.clock()
            if now < t_next:
                self._stop.wait(t_next - now)
                continue
            t_next = max(t_next + period, now)  # drop frames rather than queue them
            frame = self.capture(now - self.transport_delay_s)  # exposed d seconds ago
            if frame.t_capture == last_t:
                continue  # frozen: nothing new
            last_t = frame.t_capture
            with self._lock:
                self._new_frame_times.append(frame.t_capture)
            smp = self.estimate(frame)
            smp.t_ready = self.clock()
            with self._lock:
                self._published = smp

    def poll_frames(self) -> list[float]:
        with self._lock:
            out, self._new_frame_times = self._new_frame_times, []
        return out

    def latest_sample(self) -> PoseSample | None:
        with self._lock:
            return getattr(self, "_published", None)


def make_vision_rig(source, calibration_path, plan, cfg, session) -> CameraRig:
    if source == "sim":
        rig = ProjectedFiducialRig(plan, trajectory=cfg.trajectory, seed=cfg.seed, fps=cfg.camera_fps)
        rig.clock = session.clock
        return rig
    raise MonoTrackerError(f"camera source {source!r} needs the vision package's frame sources, "
                           "which are not wired into this build yet")
