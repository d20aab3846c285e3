"""The tracking loop's camera part: choose, start and stop the camera rig, watch its frames
(frozen, late, stalled: :meth:`CameraControl.frame_condition`), stop it when the plan changes, learn the balls' colour, inject simulated faults.

A part of :class:`~monotracker.engine.loop.core.TrackingLoop` (``loop.camera``); the pose side
(holds, the trust verdict) is the core's."""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

from monotracker.engine import rigs
from monotracker.engine.alarms import CAMERA_SETUP_CODES, POSE_CODES
from monotracker.engine.loop.heap import HeapFreeze
from monotracker.engine.snapshot import CommandResult
from monotracker.errors import MonoTrackerError


class CameraControl:
    """The camera rig of one tracking loop (see the module docstring). ``loop``: the core (holds,
    the pose, the gate); ``plan``: the plan editor (the plan the rig registers against, the camera
    and hand-eye it stores); ``session``: what the rig factory hands the rigs."""

    def __init__(self, loop, *, plan, session):
        self.loop = loop
        self.cfg = loop.cfg
        self.plan = plan
        self._session = session
        self._lock = threading.RLock()
        self.source = self.cfg.camera
        self.calibration_path: str | None = None
        saved = plan.copy()
        if saved.camera_source and saved.camera_source == self.cfg.camera:
            self.calibration_path = saved.calibration_path  # the calibration used last time
        self.rig: rigs.CameraRig | None = None
        self.rig_fiducials: np.ndarray | None = None  # the fiducial set the running rig registers against
        self.error: str | None = None
        self.fault = "none"
        self._last_frame_t: float | None = None  # capture time of the newest frame seen
        self._last_frame_seen_at: float | None = None  # session time it arrived
        self._last_digest = None  # content checksum of the newest frame (None: the rig gives none)
        self._repeat_frames = 0  # bit-identical repeats since the last new frame (a frozen camera)
        self.frames = 0
        self.frame_times: deque[float] = deque(maxlen=90)
        self.next_frame_t = 0.0  # sim clock: when the next frame is due (s)
        #: the garbage collector's heap frozen while this loop's camera runs (:mod:`.heap`)
        self.heap = HeapFreeze(self.cfg.freeze_heap)

    def now(self) -> float:
        return self.loop.now()

    def set_camera(self, source: str, calibration_path: str | None) -> CommandResult:
        """Choose the frame source (a row of ``engine/rigs/sources.py``: "sim", "sim-points",
        "device:N", "file:PATH", "folder:PATH", "replay:DIR") and optional calibration file
        (OpenCV YAML/XML or JSON); applied by :meth:`start_camera`. Refused: an unknown source, the
        camera running (stop it first), the robot tracking."""
        source = str(source)
        why = rigs.source_problem(source)
        if why:
            return CommandResult(False, why)
        if self.rig is not None and self.rig.running:
            return CommandResult(False, "stop the camera first")
        if self.loop.robot.state() == "tracking":
            return CommandResult(False, "stop tracking first")
        self.source, self.calibration_path = source, calibration_path
        self.loop.events.event("camera_set", f"camera source {source}" + (f", calibration {calibration_path}" if calibration_path else ""),
                      {"source": source, "calibration_path": calibration_path})
        return CommandResult(True, f"camera {source}")

    def start_camera(self) -> CommandResult:
        """Start the pose stream on the chosen source (own thread with clock="real"; stepped by
        :meth:`advance` with clock="sim"); poses appear in ``snap.pose``. Refused: fiducials not
        locked; the source or calibration cannot be opened (``camera_failed`` alarm); the
        calibration cannot be stored in the plan. Already running: ok."""
        plan = self.plan.copy()
        if not plan.fiducials_locked:
            return CommandResult(False, "confirm the CT fiducials before starting the camera")
        if self.rig is not None and self.rig.running:
            return CommandResult(True, "camera already running")
        # setup conditions belong to one camera: the one before (stopped by a plan change, say)
        # leaves none behind; the new rig raises its own
        self.loop.alarms.board.clear_all(CAMERA_SETUP_CODES, self.now())
        try:
            rig = rigs.make_camera_rig(self.source, self.calibration_path, plan, self.cfg, self._session)
        except MonoTrackerError as exc:
            self.error = str(exc)
            self.loop.alarms.board.clear_all(CAMERA_SETUP_CODES, self.now())   # raised by the rig that failed
            self.loop.invalidate_pose("camera could not start")
            self.loop.alarms.board.set("camera_failed", f"camera could not start: {exc}", self.now())
            self.loop.alarms.alert("alarm", "camera_failed", f"camera could not start: {exc}")
            return CommandResult(False, str(exc))
        # (not CAMERA_SETUP_CODES: the new rig raised them, and they hold while this camera runs)
        self.loop.alarms.board.clear_all(("camera_failed", "camera_stopped"), self.now())
        with self._lock:
            self.rig = rig
            self.rig_fiducials = plan.fiducial_centres().copy()  # the set this rig registers against
            self.error = None
            self._last_frame_seen_at = self.now()
            self._last_digest, self._repeat_frames = None, 0
            self.next_frame_t = self.now()
        anchor = plan.entry_lps_mm if plan.entry_lps_mm is not None else plan.fiducial_centres().mean(axis=0)
        self.loop.restart_gate(anchor)
        why = self.plan.store_camera(self.source, self.calibration_path, rig.K, rig.dist, rig.image_size)
        if why:
            self._stop_rig(rig)
            with self._lock:
                self.rig = None
                self.error = why
            return CommandResult(False, f"camera not started: {why}")
        if rig.default_T_base_cam is not None and plan.T_base_cam is None:
            self.plan.set_hand_eye(rig.default_T_base_cam)
        # no full garbage collection inside a frame while this camera runs (released by _stop_rig);
        # its one collection comes before the rig's first frame
        self.heap.hold()
        # running before the rig's threads start: what they do on its first frames (the colour
        # watch) counts; a 5-frame folder could be half read before the flag was set
        rig.running = True
        if self.cfg.clock == "real":
            try:
                rig.start()
            except BaseException:
                rig.running = False
                self.heap.release()
                raise
        self.loop.events.event("camera_started", f"camera {self.source} started",
                      {"source": self.source, "K": None if rig.K is None else np.asarray(rig.K).tolist()})
        return CommandResult(True, "camera started")

    def stop_camera(self) -> CommandResult:
        """Stop the rig; the pose is cleared and a tracking arm holds."""
        rig = self.rig
        if rig is None or not rig.running:
            return CommandResult(True, "camera not running")
        self._stop_rig(rig)
        self.loop.events.event("camera_stopped", "camera stopped")
        self.loop.alarms.board.clear_all(POSE_CODES, self.now())
        self.loop.hold("camera_stopped", "camera stopped")
        self.loop.invalidate_pose("camera stopped", hold=False)
        return CommandResult(True, "camera stopped")

    def shutdown(self) -> None:
        """The session ends: stop the rig, running or not (its setup conditions and its hold on
        the frozen heap go with it)."""
        if self.rig is not None:
            self._stop_rig(self.rig)

    def _stop_rig(self, rig) -> None:
        """Stop ``rig``; the conditions of its setup (:data:`~.alarms.CAMERA_SETUP_CODES`) go with it."""
        rig.running = False
        try:
            rig.stop()
        finally:
            self.heap.release()
        self.loop.alarms.board.clear_all(CAMERA_SETUP_CODES, self.now())

    def plan_changed(self, why: str, restart_camera: bool) -> None:
        """The plan's fiducials, path or CT changed: the pose (and a running camera rig, built with
        the old fiducials and target) belong to the old plan. Stop the camera, forget the pose and,
        if ``restart_camera`` and the camera was running, start it again on the new plan."""
        rig = self.rig
        was_running = rig is not None and rig.running
        if was_running:
            self._stop_rig(rig)
            self.loop.events.event("camera_stopped", f"camera stopped: {why}")
        self.loop.invalidate_pose(why)
        if was_running and restart_camera:
            r = self.start_camera()
            if not r.ok:
                self.loop.alarms.alert("warning", "camera_stopped", f"camera stopped ({why}) and could not restart: {r.message}")
        elif was_running:
            self.loop.hold("camera_stopped", f"camera stopped: {why}")

    def frame_condition(self, now: float) -> tuple[str, str] | None:
        """What is wrong with the camera's frames now, as ``(code, reason)`` (the arm holds for
        it), or None. Three conditions, told apart by what arrives (issue 33):

        * ``camera_freeze``: its last frame(s) repeated bit for bit (a frozen driver; sensor
          noise never repeats a frame), at the first repeat;
        * ``camera_stalled``: no new frame at all for ``stall_after_s`` (at least
          ``freeze_after_s``): a camera that stopped delivering;
        * ``camera_late``: no new frame for ``freeze_after_s`` (0.1 s, the robot's freshness rule)
          but less than ``stall_after_s``: the source is alive, its frames come late (a busy
          machine). The arm holds as for a stall, since no fresh pose can come; what differs is
          what is reported (a warning with a dwell, not a frozen-camera alarm).

        A rig that watches its own camera (StreamRig) reports these as estimates with a code: None."""
        rig = self.rig
        if rig is None or not rig.running or getattr(rig, "watches_itself", False):
            return None
        seen = self._last_frame_seen_at
        if self._repeat_frames:
            return "camera_freeze", (f"camera frozen: {self._repeat_frames} frame(s) repeated bit for bit "
                                     f"(last new frame {1000 * (now - seen):.0f} ms ago)")
        if seen is None:
            return None
        gap = now - seen
        if gap > max(self.cfg.stall_after_s, self.cfg.freeze_after_s):
            return "camera_stalled", f"camera stalled: no new frame for {1000 * gap:.0f} ms"
        if gap > self.cfg.freeze_after_s:
            fps = self.recent_fps(now)
            rate = f"{fps:.0f} fps over the last second" if fps else "frames arriving"
            return "camera_late", (f"camera late: no new frame for {1000 * gap:.0f} ms ({rate}, "
                                   f"{self.cfg.camera_fps:.0f} expected; the machine may be busy)")
        return None

    def recent_fps(self, now: float, window_s: float = 1.0) -> float:
        """New frames per second over the last ``window_s`` (s) of session time."""
        with self._lock:
            n = sum(1 for t in self.frame_times if now - t <= window_s)
        return n / window_s

    def note_frame(self, t_capture: float, now: float, digest=None) -> bool:
        """A frame with capture time ``t_capture`` arrived; True if it is new. Only new frames
        refresh the freeze watchdog (a frozen camera repeats its last frame). ``digest``: a
        checksum of the content; equal to the previous frame's, the frame is a bit-identical
        repeat (a frozen camera; sensor noise never repeats a frame) and the freeze alarm holds
        the arm at the next watchdog tick, without waiting ``freeze_after_s``."""
        with self._lock:
            if self._last_frame_t is not None and t_capture <= self._last_frame_t:
                return False
            if digest is not None and digest == self._last_digest:
                self._last_frame_t = t_capture
                self._repeat_frames += 1
                return False
            self._last_digest = digest
            self._repeat_frames = 0
            self._last_frame_t = t_capture
            self._last_frame_seen_at = now
            self.loop.alarms.board.clear("camera_freeze", now)
            self.frames += 1
            self.frame_times.append(now)
            return True

    def latest_frame(self):
        """``(image BGR uint8, frame_index, estimate)`` of the newest processed frame, or None."""
        rig = self.rig
        return None if rig is None else rig.latest_frame()

    def learn_ball_colour(self, x_px: float, y_px: float, *, frame=None, frame_index: int | None = None) -> CommandResult:
        """Learn the balls' colour from one click (pixel x, y) on a ball; the running detector uses
        it at once and the camera's calibration file keeps it. ``frame``: the BGR image clicked on;
        without it the newest frame, refused when ``frame_index`` is no longer the newest."""
        from monotracker.engine.ball_colour_cmd import learn_ball_colour_from_frame

        try:
            got = learn_ball_colour_from_frame(self.rig, self.calibration_path, x_px, y_px,
                                               frame=frame, frame_index=frame_index)
        except MonoTrackerError as exc:
            return CommandResult(False, str(exc))
        self.loop.events.event("ball_colour_learned", got.message, {**got.colour.to_dict(), "saved_to": got.saved_to})
        return CommandResult(True, got.message)

    # ================================================================== faults (sim only)
    def inject_fault(self, name: str) -> CommandResult:
        """Simulated sessions only: start fault ``name`` (``sim/faults.py``; "none" clears)."""
        from monotracker.engine.config import FAULTS

        if name not in FAULTS:
            return CommandResult(False, f"unknown fault {name!r}; use one of {', '.join(FAULTS)}")
        if name == "none":
            self.fault = "none"
            if self.rig is not None:
                self.rig.set_fault("none")
            self.loop.events.event("fault_cleared", "fault injection cleared")
            return CommandResult(True, "fault cleared")
        from monotracker.robot.backends import parse_spec

        if not (rigs.parse_source(self.source)[0].simulated and parse_spec(self.cfg.robot)[0].simulated):
            return CommandResult(False, "fault injection is for the simulated camera and arm only")
        if name == "robot-disconnect":
            rob = self.loop.robot.rig
            if rob is None:
                return CommandResult(False, "no robot to disconnect")
            rob.inject_disconnect()
        else:
            if self.rig is None:
                return CommandResult(False, "start the camera first")
            from monotracker.sim.faults import CAMERA_MOTION_FAULTS

            if name in CAMERA_MOTION_FAULTS and not getattr(self.rig, "renders_camera_motion", False):
                return CommandResult(False, f"{name} moves the rendered twin camera: use camera 'sim' "
                                            f"(this camera, {self.source}, has no background to move)")
            self.rig.set_fault(name)
        self.fault = name
        self.loop.events.event("fault_injected", f"fault injected: {name}", {"fault": name}, level="warning")
        return CommandResult(True, f"fault {name} injected")

