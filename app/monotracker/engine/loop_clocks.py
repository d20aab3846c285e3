"""The tracking loop's two clocks: ``advance`` steps the simulated clock (demo, tests,
benchmarks; see :mod:`monotracker.engine.loop` for the model), ``start_threads``/``shutdown``
run the engine thread on the real clock.

Mixed into :class:`~monotracker.engine.loop.TrackingLoop`, whose state these methods use."""

from __future__ import annotations

import logging
import threading
import time

from monotracker.engine.pipeline_priority import normal_priority, set_gil_switch_interval
from monotracker.errors import MonoTrackerError

log = logging.getLogger("monotracker.engine.loop")


class LoopClocks:
    """The simulated and the real clock of the loop (a part of :class:`~monotracker.engine.loop.TrackingLoop`)."""

    # ================================================================== sim clock
    def advance(self, dt: float) -> None:
        if dt < 0:
            raise MonoTrackerError("advance needs dt >= 0")
        period = 1.0 / self.cfg.control_hz
        frame_period = 1.0 / self.cfg.camera_fps
        n = int(round(dt / period))
        for _ in range(n):
            self._t += period
            t = self._t
            self.s.clock.set(t)
            rig = self.rig
            if rig is not None and rig.running and t + 1e-9 >= self._next_frame_t:
                self._next_frame_t += frame_period
                # frames travel in a pipeline; the estimator takes a frame when it arrives, if free
                if t + rig.transport_delay_s >= self._busy_until - 1e-12:
                    frame = rig.capture(t)
                    # A frozen camera hands back the same frame: nothing new to estimate.
                    if frame is not None and self.note_frame(frame.t_capture, t, rig.frame_digest(frame)):
                        # compute time of detection + registration: this thread's CPU time, so
                        # the model does not depend on what else the machine runs meanwhile
                        w0 = time.thread_time()
                        sample = rig.estimate(frame)
                        w = time.thread_time() - w0
                        ready = t + rig.transport_delay_s + w
                        sample.t_ready = ready
                        self._busy_until = ready
                        self._in_flight.append((ready, sample))
            while self._in_flight and self._in_flight[0][0] <= t + 1e-12:
                _, sample = self._in_flight.popleft()
                self.on_pose(sample, t)
            self.watchdogs(t)
            if self.robot is not None:
                self.robot.step(t)
                self.after_command(t)
                self._refresh_robot_state()
            for fn in self._tick_hooks:
                fn(self, t)

    # ================================================================== real clock
    def start_threads(self) -> None:
        self._threads_wanted = True
        if self.cfg.clock != "real" or self._thread is not None:
            return
        # the priority policy (engine/pipeline_priority.py): every engine-process thread keeps the
        # priority the server was started with; a waking web-server thread (a STOP) gets the GIL
        # within ~1 ms of asking
        set_gil_switch_interval()
        self.process_priority = "normal priority (the engine process is never raised)"
        if self.robot is not None:
            self.robot.start_thread()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="monotracker-loop", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        # the engine thread (estimate -> trust -> target, watchdogs): normal, like the web server
        self.priority = normal_priority(int(getattr(self.cfg, "pose_nice", 0)))
        period = 1.0 / 250.0
        last_seen = None
        while not self._stop.is_set():
            now = self.now()
            rig = self.rig
            woke = getattr(rig, "new_sample", None)  # a rig that signals new samples wakes us at once
            if woke is not None:
                woke.clear()
            try:
                if rig is not None and rig.running:
                    for frame_t, digest in rig.poll_frame_info():
                        self.note_frame(frame_t, now, digest)
                    sample = rig.latest_sample()
                    if sample is not None and sample is not last_seen:
                        last_seen = sample
                        self.on_pose(sample, now)
                self.watchdogs(now)
                if self.robot is not None and self._pending_latency_stamp is not None:
                    st = self.robot.status()
                    # the first control step after the target was handed over used it
                    if st.t_command is not None and st.t_command >= self._pending_latency_set_at:
                        self.after_command(st.t_command)
                self.s._alarm_board.clear("engine_error", now)
            except Exception:  # the loop must survive; hold the arm and report
                log.exception("engine loop iteration failed")
                self._on_iteration_error()
            if woke is not None:
                woke.wait(period)
            else:
                self._stop.wait(period)

    def _on_iteration_error(self) -> None:
        """After a failed loop iteration: hold the arm and raise the alarm. If holding itself fails
        (e.g. the robot call that failed is the one the hold needs), stop tracking outright so an
        exception can never leave the arm following the last target; the loop thread survives."""
        try:
            self._hold("engine_error", "internal engine error; arm holding (see log)")
        except Exception:  # last resort, must not kill the engine thread
            log.exception("holding after an engine error failed; stopping tracking")
            try:
                if self.robot is not None:
                    self.robot.stop_tracking()
            except Exception:
                log.exception("stop_tracking after an engine error failed")

    def shutdown(self) -> None:
        self._stop.set()
        th = self._thread
        if th is not None:
            th.join(2.0)
            self._thread = None
        if self.robot is not None:
            try:
                if self.robot_state() in ("tracking", "holding"):
                    self.robot.stop_tracking()
                self.robot.disarm()
            finally:
                self.robot.close()
        if self.rig is not None:
            self.rig.running = False
            self.rig.stop()
