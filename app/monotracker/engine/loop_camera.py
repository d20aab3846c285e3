"""The tracking loop's camera commands: choose, start and stop the camera, forget the pose when
the plan changes, inject simulated faults.

Mixed into :class:`~monotracker.engine.loop.TrackingLoop`, whose state these methods use."""

from __future__ import annotations

import numpy as np

from monotracker.engine import components
from monotracker.engine.alarms import CAMERA_SETUP_CODES, POSE_CODES
from monotracker.engine.snapshot import CommandResult
from monotracker.errors import MonoTrackerError


class CameraCommands:
    """The tracking loop's camera commands: choose, start and stop the camera, forget the pose when (a part of :class:`~monotracker.engine.loop.TrackingLoop`)."""

    def set_camera(self, source: str, calibration_path: str | None) -> CommandResult:
        source = str(source)
        if not (source in ("sim", "sim-points") or source.split(":", 1)[0] in ("device", "file", "folder", "replay")):
            return CommandResult(False, "camera must be 'sim', 'sim-points', 'device:N', 'file:PATH', 'folder:PATH' "
                                 "or 'replay:DIR'")
        if self.rig is not None and self.rig.running:
            return CommandResult(False, "stop the camera first")
        if self.robot_state() == "tracking":
            return CommandResult(False, "stop tracking first")
        self.camera_source, self.calibration_path = source, calibration_path
        self.s.record("camera_set", f"camera source {source}" + (f", calibration {calibration_path}" if calibration_path else ""),
                      {"source": source, "calibration_path": calibration_path})
        return CommandResult(True, f"camera {source}")

    def start_camera(self) -> CommandResult:
        plan = self.s.plan_copy()
        if not plan.fiducials_locked:
            return CommandResult(False, "confirm the CT fiducials before starting the camera")
        if self.rig is not None and self.rig.running:
            return CommandResult(True, "camera already running")
        # setup conditions belong to one camera: the one before (stopped by a plan change, say)
        # leaves none behind; the new rig raises its own
        self.s._alarm_board.clear_all(CAMERA_SETUP_CODES, self.now())
        try:
            rig = components.make_camera_rig(self.camera_source, self.calibration_path, plan, self.cfg, self.s)
        except MonoTrackerError as exc:
            self.camera_error = str(exc)
            self.s._alarm_board.clear_all(CAMERA_SETUP_CODES, self.now())   # raised by the rig that failed
            self.invalidate_pose("camera could not start")
            self.s._alarm_board.set("camera_failed", f"camera could not start: {exc}", self.now())
            self.s.alert("alarm", "camera_failed", f"camera could not start: {exc}")
            return CommandResult(False, str(exc))
        # (not CAMERA_SETUP_CODES: the new rig raised them, and they hold while this camera runs)
        self.s._alarm_board.clear_all(("camera_failed", "camera_stopped"), self.now())
        with self._lock:
            self.rig = rig
            self._rig_fiducials = plan.fiducial_centres().copy()  # the set this rig registers against
            self.camera_error = None
            self._last_frame_seen_at = self.now()
            self._last_digest, self._repeat_frames = None, 0
            self._next_frame_t = self.now()
            self.gate.reset()
            anchor = plan.entry_lps_mm if plan.entry_lps_mm is not None else plan.fiducial_centres().mean(axis=0)
            self.gate.set_anchor(anchor)
        why = self.s._store_camera(self.camera_source, self.calibration_path, rig.K, rig.dist, rig.image_size)
        if why:
            self._stop_rig(rig)
            with self._lock:
                self.rig = None
                self.camera_error = why
            return CommandResult(False, f"camera not started: {why}")
        if rig.default_T_base_cam is not None and plan.T_base_cam is None:
            self.s.set_hand_eye(rig.default_T_base_cam)
        if self.cfg.clock == "real":
            rig.start()
        rig.running = True
        self.s.record("camera_started", f"camera {self.camera_source} started",
                      {"source": self.camera_source, "K": None if rig.K is None else np.asarray(rig.K).tolist()})
        return CommandResult(True, "camera started")

    def stop_camera(self) -> CommandResult:
        rig = self.rig
        if rig is None or not rig.running:
            return CommandResult(True, "camera not running")
        self._stop_rig(rig)
        self.s.record("camera_stopped", "camera stopped")
        self.s._alarm_board.clear_all(POSE_CODES, self.now())
        self._hold("camera_stopped", "camera stopped")
        self.invalidate_pose("camera stopped", hold=False)
        return CommandResult(True, "camera stopped")

    def _stop_rig(self, rig) -> None:
        """Stop ``rig``; the conditions of its setup (:data:`~.alarms.CAMERA_SETUP_CODES`) go with it."""
        rig.running = False
        rig.stop()
        self.s._alarm_board.clear_all(CAMERA_SETUP_CODES, self.now())

    def invalidate_pose(self, why: str, hold: bool = True) -> None:
        """Forget the pose: it no longer belongs to the current plan/camera (new CT, new plan,
        fiducials or path changed, camera stopped or failed). ``snap.pose`` becomes None, the trust
        gate starts over (first lock needs ``confirm_frames`` consistent estimates), and an engaged
        arm holds (``hold``) until a pose for *this* plan is trusted."""
        with self._lock:
            had = self._latest is not None
            self._latest = self._last_trusted = None
            self._fresh_since = None
            self._seen_ids = None
            self.gate.reset()
        if hold and self.robot_state() in ("tracking", "holding"):
            self._hold("pose_lost", f"pose cleared: {why}")
        if had:
            self.s.record("pose_invalidated", f"pose cleared: {why}", {"why": why})

    def plan_changed(self, why: str, restart_camera: bool) -> None:
        """The plan's fiducials, path or CT changed: the pose (and a running camera rig, built with
        the old fiducials and target) belong to the old plan. Stop the camera, forget the pose and,
        if ``restart_camera`` and the camera was running, start it again on the new plan."""
        rig = self.rig
        was_running = rig is not None and rig.running
        if was_running:
            self._stop_rig(rig)
            self.s.record("camera_stopped", f"camera stopped: {why}")
        self.invalidate_pose(why)
        if was_running and restart_camera:
            r = self.start_camera()
            if not r.ok:
                self.s.alert("warning", "camera_stopped", f"camera stopped ({why}) and could not restart: {r.message}")
        elif was_running:
            self._hold("camera_stopped", f"camera stopped: {why}")

    def latest_frame(self):
        rig = self.rig
        return None if rig is None else rig.latest_frame()

    # ================================================================== faults (sim only)
    def inject_fault(self, name: str) -> CommandResult:
        if name == "none":
            self.fault = "none"
            if self.rig is not None:
                self.rig.set_fault("none")
            self.s.record("fault_cleared", "fault injection cleared")
            return CommandResult(True, "fault cleared")
        if not self.camera_source.startswith("sim") or self.cfg.robot != "sim":
            return CommandResult(False, "fault injection is for the simulated camera and arm only")
        if name == "robot-disconnect":
            if self.robot is None:
                return CommandResult(False, "no robot to disconnect")
            self.robot.inject_disconnect()
        else:
            if self.rig is None:
                return CommandResult(False, "start the camera first")
            self.rig.set_fault(name)
        self.fault = name
        self.s.record("fault_injected", f"fault injected: {name}", {"fault": name}, level="warning")
        return CommandResult(True, f"fault {name} injected")

