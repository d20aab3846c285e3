"""Is the pose pipeline keeping up with the camera on this machine? (``pipeline_overloaded``)

A pose goes stale (older than ``max_pose_age_s``) for one of three reasons: the camera stopped
delivering (``camera_freeze``, the camera part's watchdog), the camera delivers late frames, or
the frames arrive and this machine cannot estimate them in time: detection + registration (and,
for the twin, its render on the same CPU) take longer than a frame period, so frames are dropped
and every pose is old when it comes. The last is not a camera fault and must not read as one:
:class:`PipelineLoad` keeps the last second of frames and estimates and says when the pipeline
is the cause, with the figures the operator can act on (close other programs, a faster machine).

Fed by the loop core: :meth:`PipelineLoad.note_pose` with every estimate (its capture and ready
times, session s); the camera part's ``frame_times`` (session s of every new frame) is read at
the verdict. Units: s, session clock.
"""

from __future__ import annotations

from collections import deque

import numpy as np


class PipelineLoad:
    """The pose pipeline's load over the last ``window_s`` seconds (see the module docstring)."""

    def __init__(self, window_s: float = 1.0):
        self.window_s = float(window_s)
        self._poses: deque[tuple[float, float]] = deque(maxlen=256)  # (arrived s, pipeline s)

    def note_pose(self, t_capture: float, t_ready: float | None, now: float, transport_delay_s: float,
                  pipeline_s: float | None = None) -> None:
        """An estimate of the frame captured at ``t_capture`` became ready at ``t_ready`` (None:
        unknown, then ``now``) and reached the loop at ``now``; ``transport_delay_s``: the
        camera's own capture -> frame-in-memory delay, which is not the pipeline's.
        ``pipeline_s``: the pipeline's own time for it when the driver measured it (the
        simulated clock's compute time), else ready - capture - transport."""
        if pipeline_s is None:
            ready = now if t_ready is None else float(t_ready)
            pipeline_s = ready - float(t_capture) - float(transport_delay_s)
        self._poses.append((float(now), max(0.0, float(pipeline_s))))

    def overloaded(self, now: float, frame_times, frame_period_s: float) -> str | None:
        """The reason line when the pipeline, not the camera, makes the poses late: in the last
        ``window_s`` the camera delivered frames (``frame_times``, session s: at least 2; its rate
        measured from them, ``frame_period_s`` s when too few) and the pipeline
        either estimated fewer than 3 in 4 of them or took longer than a frame period for one
        of its last 3 estimates; None otherwise. Asked only when the pose is stale."""
        lo = now - self.window_s
        seen = [t for t in list(frame_times) if lo < t <= now]
        frames = len(seen)
        if frames >= 4:   # the camera's own rate (a real camera may not run at the configured one)
            frame_period_s = float(np.median(np.diff(seen)))
        if frames < 2:
            return None       # the camera is not delivering: its own watchdog says so
        recent = [p for a, p in list(self._poses) if lo < a <= now]
        done = len(recent)
        # the newest estimates say what the pipeline does now (a machine that just got busy: the
        # second before was fast); when poses are stale, one of the last 3 over a frame period
        # is the cause (a single spike does not age a pose past the limit)
        busy = max(recent[-3:]) if recent else float("inf")
        if done >= 0.75 * frames and busy <= frame_period_s:
            return None
        busy_txt = "none finished" if not recent else f"the last took up to {1000 * busy:.0f} ms"
        return (f"this computer is too slow for the pose pipeline: it estimated {done} of the {frames} frames "
                f"of the last {self.window_s:g} s ({busy_txt}; a frame comes every {1000 * frame_period_s:.0f} ms), "
                "so poses arrive late: the arm holds until it keeps up (close other programs or use a faster "
                "computer; the camera itself delivers frames)")
