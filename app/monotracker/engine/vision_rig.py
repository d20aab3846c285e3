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

from monotracker.engine.components import CameraRig, estimate_to_sample
from monotracker.engine.sim_rigs import (DRAPE_BGR, SIM_DIST, SIM_FOCAL_PX, SIM_IMAGE_SIZE,
                                         SIM_TRANSPORT_DELAY_S, SKIN_BGR, ProjectedFiducialRig, SimFrame,
                                         SimImageRig)
from monotracker.engine.stream_rig import StreamRig
from monotracker.errors import MonoTrackerError

__all__ = ["DRAPE_BGR", "SIM_DIST", "SIM_FOCAL_PX", "SIM_IMAGE_SIZE", "SIM_TRANSPORT_DELAY_S", "SKIN_BGR",
           "ProjectedFiducialRig", "SimFrame", "SimImageRig", "StreamRig", "estimate_to_sample", "make_vision_rig"]


def make_vision_rig(source, calibration_path, plan, cfg, session) -> CameraRig:
    if source in ("sim", "sim-points"):
        if source == "sim":
            rig = SimImageRig(plan, trajectory=cfg.trajectory, seed=cfg.seed, fps=cfg.camera_fps,
                              optics=getattr(cfg, "camera_optics", None))
        else:
            rig = ProjectedFiducialRig(plan, trajectory=cfg.trajectory, seed=cfg.seed, fps=cfg.camera_fps)
        rig.clock = session.clock
        rig.nice = int(getattr(cfg, "pose_nice", 0))  # >= 0 (SessionConfig.validate): never above the web server
        rig.camera_process = bool(getattr(cfg, "sim_camera_process", False)) and cfg.clock == "real"
        if getattr(rig, "tracker", None) is not None:
            rig.tracker.config.max_predicted_tre_mm = float(cfg.max_predicted_tre_mm)
    else:
        if cfg.clock != "real":
            raise MonoTrackerError("real cameras need a real-clock session (clock='real')")
        rig = StreamRig(source, calibration_path, plan, session, camera_adapt=cfg.camera_adapt,
                        max_predicted_tre_mm=cfg.max_predicted_tre_mm)
    rig.validation.limit_mm = float(cfg.max_validation_tre_mm)
    return rig
