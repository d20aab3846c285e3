"""What drives the tracking loop: :class:`SimStepper` steps the simulated clock (demo, tests,
benchmarks; the model is in :mod:`monotracker.engine.loop.core`), :class:`RealThread` runs the
engine thread on the real clock. :class:`SimClock` is the settable session clock of
clock="sim" sessions. Each driver is a part of :class:`~monotracker.engine.loop.core.TrackingLoop`
(``loop.driver``)."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

from monotracker.engine.pipeline_priority import normal_priority, set_gil_switch_interval
from monotracker.errors import MonoTrackerError

log = logging.getLogger("monotracker.engine.loop")


class SimClock:
    """A settable clock (s) for clock="sim" sessions."""

    def __init__(self, t0: float = 0.0):
        self._t = float(t0)
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            return self._t

    def set(self, t: float) -> None:
        """Set the simulated time, s."""
        with self._lock:
            self._t = float(t)


class SimStepper:
    """clock="sim": no threads; :meth:`advance` steps the session's :class:`SimClock` at the
    control period, a frame every camera period when the estimator is free (see the core's
    module docstring for the latency model)."""

    def __init__(self, loop):
        self.loop = loop
        self._t = 0.0
        self._busy_until = -1.0
        self._in_flight: deque[tuple[float, object]] = deque()

    def start(self) -> None:
        pass  # nothing runs by itself on the simulated clock

    def stop(self) -> None:
        pass

    def advance(self, dt: float) -> None:
        if dt < 0:
            raise MonoTrackerError("advance needs dt >= 0")
        loop = self.loop
        cam, robot = loop.camera, loop.robot
        period = 1.0 / loop.cfg.control_hz
        frame_period = 1.0 / loop.cfg.camera_fps
        charge = getattr(loop.cfg, "compute_charge_s", None)
        charge = None if charge is None else float(charge)
        n = int(round(dt / period))
        for _ in range(n):
            self._t += period
            t = self._t
            loop.clock.set(t)
            rig = cam.rig
            if rig is not None and rig.running and t + 1e-9 >= cam.next_frame_t:
                cam.next_frame_t += frame_period
                # frames travel in a pipeline; the estimator takes a frame when it arrives, if free
                if t + rig.transport_delay_s >= self._busy_until - 1e-12:
                    frame = rig.capture(t)
                    # A frozen camera hands back the same frame: nothing new to estimate.
                    if frame is not None and cam.note_frame(frame.t_capture, t, rig.frame_digest(frame)):
                        # compute time of detection + registration: this thread's CPU time, so
                        # the model does not depend on what else the machine runs meanwhile, or
                        # the fixed charge the session asked for (SessionConfig.compute_charge_s)
                        w0 = time.thread_time()
                        sample = rig.estimate(frame)
                        w = time.thread_time() - w0 if charge is None else charge
                        ready = t + rig.transport_delay_s + w
                        sample.t_ready = ready
                        sample.stages["pipeline_s"] = w   # the pipeline's own time (engine/loop/load.py)
                        # the work deferred until the pose is out (a due frame's camera-motion
                        # check): the estimator is busy with it after the pose is ready, so it
                        # delays the next frame, never this pose (a fixed charge covers it all)
                        a0 = time.thread_time()
                        rig.after_publish()
                        after = time.thread_time() - a0 if charge is None else 0.0
                        sample.stages["after_pose_s"] = after
                        self._busy_until = ready + after
                        self._in_flight.append((ready, sample))
            while self._in_flight and self._in_flight[0][0] <= t + 1e-12:
                _, sample = self._in_flight.popleft()
                loop.on_pose(sample, t)
            loop.watchdogs(t)
            rob = robot.rig
            if rob is not None:
                rob.step(t)
                loop.after_command(t)
                robot.refresh()
            loop.run_tick_hooks(t)


class RealThread:
    """clock="real": the engine thread (``monotracker-loop``, 250 Hz) hands each new estimate to
    the core and runs the watchdogs; the robot's control runs on its own thread or process."""

    def __init__(self, loop):
        self.loop = loop
        self.cfg = loop.cfg
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.priority = ""  # what the OS granted the engine thread (pipeline_priority)
        self.process_priority = ""  # ... and the engine process's threads

    def advance(self, dt: float) -> None:
        raise MonoTrackerError("advance() is only for clock='sim' sessions")

    def start(self) -> None:
        self.loop.robot.threads_wanted = True
        if self._thread is not None:
            return
        # the priority policy (engine/pipeline_priority.py): every engine-process thread keeps the
        # priority the server was started with; a waking web-server thread (a STOP) gets the GIL
        # within ~1 ms of asking
        set_gil_switch_interval()
        self.process_priority = "normal priority (the engine process is never raised)"
        rob = self.loop.robot.rig
        if rob is not None:
            rob.start_thread()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="monotracker-loop", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        # the engine thread (estimate -> trust -> target, watchdogs): normal, like the web server
        self.priority = normal_priority(int(getattr(self.cfg, "pose_nice", 0)))
        loop, cam = self.loop, self.loop.camera
        period = 1.0 / 250.0
        last_seen = None
        while not self._stop.is_set():
            now = loop.now()
            rig = cam.rig
            woke = getattr(rig, "new_sample", None)  # a rig that signals new samples wakes us at once
            if woke is not None:
                woke.clear()
            try:
                if rig is not None and rig.running:
                    for frame_t, digest in rig.poll_frame_info():
                        cam.note_frame(frame_t, now, digest)
                    sample = rig.latest_sample()
                    if sample is not None and sample is not last_seen:
                        last_seen = sample
                        loop.on_pose(sample, now)
                loop.watchdogs(now)
                rob = loop.robot.rig
                pending = loop.pending_latency()
                if rob is not None and pending is not None:
                    st = rob.status()
                    # the first control step after the target was handed over used it
                    if st.t_command is not None and st.t_command >= pending:
                        loop.after_command(st.t_command)
                loop.alarms.board.clear("engine_error", now)
            except Exception:  # the loop must survive; hold the arm and report
                log.exception("engine loop iteration failed")
                self.on_iteration_error()
            if woke is not None:
                woke.wait(period)
            else:
                self._stop.wait(period)

    def on_iteration_error(self) -> None:
        """After a failed loop iteration: hold the arm and raise the alarm. If holding itself fails
        (e.g. the robot call that failed is the one the hold needs), stop tracking outright so an
        exception can never leave the arm following the last target; the loop thread survives."""
        try:
            self.loop.hold("engine_error", "internal engine error; arm holding (see log)")
        except Exception:  # last resort, must not kill the engine thread
            log.exception("holding after an engine error failed; stopping tracking")
            try:
                rob = self.loop.robot.rig
                if rob is not None:
                    rob.stop_tracking()
            except Exception:
                log.exception("stop_tracking after an engine error failed")

    def stop(self) -> None:
        """Stop the engine thread (waits up to 2 s)."""
        self._stop.set()
        th = self._thread
        if th is not None:
            th.join(2.0)
            self._thread = None
