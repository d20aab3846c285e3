"""The session's camera, robot, export and recording commands.

Each delegates to the tracking loop (:mod:`monotracker.engine.loop`) or to the module that does the
work; units and frames are given on each method. Mixed into
:class:`~monotracker.engine.session.Session`, whose state these methods use."""

from __future__ import annotations

from pathlib import Path

from monotracker.engine.config import FAULTS
from monotracker.engine.plan_commands import _fail, _ok
from monotracker.engine.snapshot import CommandResult
from monotracker.errors import MonoTrackerError


class RigCommands:
    """The session's camera, robot, export and recording commands (part of :class:`~monotracker.engine.session.Session`)."""

    # ================================================================== camera
    def set_camera(self, source: str, calibration_path: str | None = None) -> CommandResult:
        """Choose the frame source (and optional calibration file); applied by ``start_camera``.

        Args:
            source: "sim", "sim-points", "device:N", "file:PATH" (video), "folder:PATH"
                (images) or "replay:DIR" (a session recording).
            calibration_path: OpenCV YAML/XML or JSON intrinsics
                (:meth:`~monotracker.vision.camera_model.CameraModel.load`); None for the
                simulated camera (it knows its own) or a recording.

        Refuses (ok=False, message): an unknown source kind; the camera is running (stop it
        first); the robot is tracking. A bad calibration file is refused by :meth:`start_camera`.
        """
        return self._loop.set_camera(source, calibration_path)

    def start_camera(self) -> CommandResult:
        """Start the pose stream on the source of :meth:`set_camera` (its own thread with
        clock="real"; stepped by :meth:`advance` with clock="sim"). Poses appear in ``snap.pose``.

        Refuses (ok=False, message): the fiducials are not confirmed (locked); the source or
        its calibration cannot be opened or read (also raised as the ``camera_failed`` alarm; the
        pose is cleared);
        the calibration cannot be stored in the plan. Already running: ok.
        """
        return self._loop.start_camera()

    def stop_camera(self) -> CommandResult:
        """Stop the pose stream; the pose is cleared (``snap.pose`` None) and a tracking arm holds.
        Not running: ok. Never refused."""
        return self._loop.stop_camera()

    def latest_frame(self):
        """``(image BGR uint8, frame_index, PoseEstimate)`` of the newest processed frame, or None."""
        return self._loop.latest_frame()

    def learn_ball_colour(self, x_px: float, y_px: float, *, frame=None, frame_index: int | None = None) -> CommandResult:
        """Learn the balls' colour from one click (pixel x, y) on a ball; the running detector uses
        it at once and the camera's calibration file keeps it. ``frame``: the BGR image the user
        clicked on (the UI passes the one it showed); without it the newest camera frame, refused
        when ``frame_index`` is given and the newest frame is no longer that one."""
        from monotracker.engine.ball_colour_cmd import learn_ball_colour_from_frame

        try:
            got = learn_ball_colour_from_frame(self._loop.rig, self._loop.calibration_path, x_px, y_px,
                                               frame=frame, frame_index=frame_index)
        except MonoTrackerError as exc:
            return _fail(str(exc))
        self._bus.event("ball_colour_learned", got.message, {**got.colour.to_dict(), "saved_to": got.saved_to})
        return _ok(got.message)

    # ================================================================== robot
    def arm(self, pin) -> CommandResult:
        """Arm the robot; ``pin`` is the operator PIN (wrong tries count towards the lockout).

        Refuses (ok=False, message): a wrong PIN or a running PIN lockout; the plan is not
        ready (:meth:`plan_not_ready`, e.g. fiducials not confirmed, no path, integrity alarm);
        a validation fiducial off its ray by more than ``config.max_validation_tre_mm`` or not
        seen (a verification report is written either way); the robot cannot be reached.
        """
        r = self._check_pin(pin, "arm_refused", "arming")
        if not r.ok:
            return r
        from monotracker.engine import verification

        why = verification.arm_refusal(self)
        try:
            verification.write_report(self, "refused" if why else "armed", why)
        except OSError as exc:
            self._bus.alert("warning", "verification_not_saved", f"verification report not saved: {exc}")
        if why:
            self._bus.alert("warning", "arm_refused", f"arming refused: {why}")
            return _fail(why)
        return self._loop.arm()

    def disarm(self) -> CommandResult:
        """Disarm the robot from armed, tracking or holding (the arm decelerates to rest).
        Refused (ok=False, message) while the e-stop is latched (reset it first); no robot: ok."""
        return self._loop.disarm()

    def start_tracking(self) -> CommandResult:
        """The arm starts following the planned path as the head moves (APFF tracker).

        Refuses (ok=False, message): not armed; the plan is not ready or changed since the
        camera started; no hand-eye calibration (``T_base_cam``); no trusted pose younger than
        ``config.max_pose_age_s`` (on a real clock it waits up to ``config.start_wait_s`` for one
        while poses keep arriving); the robot refuses (its message).
        """
        return self._loop.start_tracking()

    def stop_tracking(self) -> CommandResult:
        """The arm stops following and holds, still armed. Not tracking: ok."""
        return self._loop.stop_tracking()

    def estop(self) -> CommandResult:
        """Emergency stop: the arm stops at once and the stop is latched (``alarm`` ``estop``)
        until :meth:`reset_estop`. Never refused, also without a robot. The stop goes first,
        straight to the robot's controller (:meth:`request_estop`); the call then waits (about a
        second at most) for the controller's acknowledgement: ``ok`` when it confirmed the stop,
        else ``ok=False`` with the ``estop_unconfirmed`` alarm (use the robot's own e-stop)."""
        return self._loop.estop()

    def request_estop(self) -> None:
        """The stop channel alone: latch the e-stop in the robot's controller and return at once,
        without a lock the engine or vision may hold, without waiting for the acknowledgement or
        writing the audit (:meth:`estop` does both). For a web server's event loop, so a STOP is
        never queued behind other work (``engine/pipeline_priority.py``). Never raises."""
        self._loop.signal_estop()

    def reset_estop(self) -> CommandResult:
        """Release a latched e-stop; the arm is left disarmed (arm again to move it). Refused
        (ok=False, message) when the robot refuses the reset; no robot: ok."""
        return self._loop.reset_estop()

    def connect_robot(self) -> CommandResult:
        """Connect the arm (sim or real) without arming it, e.g. to record hand-eye poses in the
        browser's Calibrate step; the robot stays DISARMED (arming connects it too)."""
        try:
            rob = self._loop._ensure_robot()
        except MonoTrackerError as exc:
            return _fail(str(exc))
        st = rob.status()
        return _ok("robot connected (disarmed)") if st.connected else _fail(f"robot not connected: {st.message}")

    def inject_fault(self, name: str) -> CommandResult:
        """Simulated sessions only: start a fault (see ``monotracker.sim.faults``).

        ``name``: one of ``FAULTS`` ("camera-freeze", "occlude-all", "robot-disconnect",
        "bad-pose", ...; "none" clears). Refused (ok=False, message) for an unknown name, a real
        camera or robot, or "robot-disconnect" without a robot."""
        if name not in FAULTS:
            return _fail(f"unknown fault {name!r}; use one of {', '.join(FAULTS)}")
        return self._loop.inject_fault(name)

    # ================================================================== export
    def export_slicer_markups(self, folder) -> list[Path]:
        """Write fiducials and path as 3D Slicer markups (``.mrk.json``, LPS); returns the files."""
        from monotracker.engine.slicer import write_markups

        return write_markups(self.plan_copy(), Path(folder))

    # ================================================================== recording
    def start_recording(self, folder) -> CommandResult:
        """Record every estimated frame and what the engine made of it into ``folder`` (an empty or
        new folder; layout in ``docs/interop.md``) until :meth:`stop_recording` or shutdown."""
        from monotracker.interop.recording import start_session_recording

        return start_session_recording(self, folder)

    def stop_recording(self) -> CommandResult:
        """Close the recording (manifest marked complete). Idempotent."""
        from monotracker.interop.recording import stop_session_recording

        return stop_session_recording(self)

    def _recording_summary(self):
        rec = self._recorder
        return None if rec is None else rec.snapshot_summary()
