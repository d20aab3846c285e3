"""Who runs at which priority: the one place MonoTracker's scheduling policy is written down.

**STOP outranks everything.** A press of STOP must reach the robot's control process and stop
the arm whatever the camera, vision and the machine are doing (issue 34). On a 2-core machine the
old policy (the simulated camera process and the pose-pipeline thread at SCHED_FIFO 5, every
engine thread at nice -10) starved the web server that receives the press: a STOP click took
4-8 s to reach the engine and 25-35 s to show on the page. The policy now:

=====================================  ===================  ==========================================
what                                   where                priority
=====================================  ===================  ==========================================
robot control loop (8 ms cycles),      control process      SCHED_FIFO :data:`CONTROL_FIFO_PRIORITY`
its e-stop watcher (wakes on the       (``robot/control_    where the OS allows, else nice
shared stop event and latches the      process.py``)        :data:`CONTROL_FALLBACK_NICE`, else normal
stop), command and event threads                            with a ``control_priority`` warning
web server (viser's event loop, the    engine process       the priority the server was started with
STOP handler, callback workers), the                        (normal); never raised by us
engine loop, the pose pipeline, the
overlay and render threads
simulated camera renderer              its own process      normal (SCHED_OTHER, nice
                                       (``sim_camera_       ``max(inherited, 0)``): it stands in for
                                       process.py``)        camera hardware, which costs the app no CPU
=====================================  ===================  ==========================================

Real-time scheduling is for the control process only: it is small, its cycle is bounded (it
sleeps most of each 8 ms period), and it is the process that stops the arm, so it must run the
instant its stop event is set. Vision and the simulated camera never run above the web server
and the stop path; ``SessionConfig.pose_nice`` may *lower* the pose pipeline (0-19), never raise
it, and ``SessionConfig.pose_rt_priority`` only accepts 0 (the field stays so that an old
setting is refused with this reason instead of silently ignored). A camera process or pipeline
thread that inherited a raised priority (a server started under ``chrt`` or ``nice -n -5``)
drops it (:func:`normal_priority`).

The STOP path itself (``ui/status_panel.py`` -> ``Session.request_estop`` ->
``ControlProcess.signal_estop``) runs on viser's event-loop thread, never queued behind callback
workers or an engine lock: it writes a request number into shared memory and sets the shared
event the control process's e-stop watcher waits on. The page shows E-STOPPED from the control
process's own acknowledgement (the request number echoed in its published state), not from the
engine's wish.

Within the engine process all threads share one GIL, so they keep one priority: a thread at a
lower priority holding the GIL would stall the web server behind the load beside the app. The
GIL switch interval is lowered to :data:`GIL_SWITCH_INTERVAL_S` on a real-clock session so a
waking web-server thread (a STOP) waits at most ~1 ms for a busy pipeline thread to hand the GIL
over, not Python's default 5 ms.

Measured (``benchmarks/stop_latency.py``, ``benchmarks/control_jitter.py``): see the tables in
those scripts' output and in the issue notes.

Only Linux has per-thread scheduling attributes; elsewhere nothing is changed.
"""

from __future__ import annotations

import numbers
import os
import sys

#: SCHED_FIFO priority of the robot's control process (``ControlProcess`` opts ``fifo_priority``)
CONTROL_FIFO_PRIORITY = 10
#: the control process's nice value where the OS refuses SCHED_FIFO
CONTROL_FALLBACK_NICE = -10
#: the pose pipeline's default nice value (``SessionConfig.pose_nice``): normal, the web server's
DEFAULT_POSE_NICE = 0
#: the GIL switch interval of a real-time-clock engine process (s; Python's default is 5 ms)
GIL_SWITCH_INTERVAL_S = 0.001

_POLICY = "engine/pipeline_priority.py"


def pose_priority_problem(pose_nice, pose_rt_priority) -> str | None:
    """One line saying why a configured pose-pipeline priority breaks the policy, or None.
    (``SessionConfig.validate`` raises it as an ``InputError``.)"""
    for name, v in (("pose_rt_priority", pose_rt_priority), ("pose_nice", pose_nice)):
        if isinstance(v, bool) or not isinstance(v, numbers.Integral):
            return f"{name} must be a whole number, not {v!r}"
    pose_nice, pose_rt_priority = int(pose_nice), int(pose_rt_priority)
    if pose_rt_priority != 0:
        return (f"pose_rt_priority must be 0, not {pose_rt_priority}: real-time scheduling is for the robot's "
                f"control process only; vision never runs above the web server and the STOP path ({_POLICY})")
    if not 0 <= pose_nice <= 19:
        return (f"pose_nice must be a nice value from 0 (normal) to 19, not {pose_nice}: the pose pipeline may "
                f"run below the web server and the STOP path, never above them ({_POLICY})")
    return None


def normal_priority(nice: int = 0) -> str:
    """The *calling thread* at normal scheduling (SCHED_OTHER) with a nice value of at least
    ``nice`` (0-19): drops a real-time policy or a negative nice value it inherited (lowering is
    always allowed), never raises it. Threads it starts later inherit the result. Returns one
    line saying what it runs at (``"normal priority (nice 0)"``)."""
    nice = max(0, min(19, int(nice)))
    if not sys.platform.startswith("linux") or not hasattr(os, "sched_getscheduler"):
        return f"normal priority (not changed on {sys.platform})"
    notes = []
    try:
        if os.sched_getscheduler(0) not in (os.SCHED_OTHER, getattr(os, "SCHED_BATCH", -1),
                                            getattr(os, "SCHED_IDLE", -1)):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            notes.append("dropped an inherited real-time policy")
    except OSError as exc:
        notes.append(f"real-time policy could not be dropped ({exc.strerror or exc})")
    import threading

    tid = threading.get_native_id()
    try:
        current = os.getpriority(os.PRIO_PROCESS, tid)
        if current < nice:
            os.setpriority(os.PRIO_PROCESS, tid, nice)
            current = nice
    except OSError as exc:
        notes.append(f"nice {nice} refused ({exc.strerror or exc})")
        current = None
    head = "normal priority" + (f" (nice {current})" if current is not None else "")
    return head + ("; " + "; ".join(notes) if notes else "")


def set_gil_switch_interval(interval_s: float = GIL_SWITCH_INTERVAL_S) -> float:
    """Lower the interpreter's GIL switch interval to ``interval_s`` (never raise it); returns it.

    Detection and registration release the GIL in every OpenCV/NumPy call; each time the web
    server's event loop wants the GIL back (a STOP, a click) it waits up to the switch interval
    for the thread holding it. At 1 ms instead of 5 ms a waking web-server thread gets it sooner,
    and a frame's estimate on a loaded machine stays close to its CPU time
    (``benchmarks/pose_latency.py``)."""
    if sys.getswitchinterval() > interval_s:
        sys.setswitchinterval(interval_s)
    return sys.getswitchinterval()
