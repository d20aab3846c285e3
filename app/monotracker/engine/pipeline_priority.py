"""Scheduling priority of the pose pipeline's threads (camera -> detection -> registration -> target).

On a loaded machine (2 cores, CPU hogs beside the app) a thread at normal priority gets a fair
share of a core, about a third with 4 hogs, and one frame's ~25 ms of detection + registration
then takes ~80 ms of wall time: trusted poses reach the control side older than
``max_pose_age_s`` and the arm (rightly) holds. The robot's control loop already runs in its own
process at SCHED_FIFO (``robot/control_process.py``); the pose pipeline is raised below it:
the pipeline thread, the engine thread that feeds the target and the sim camera process at
SCHED_FIFO ``pose_rt_priority`` (5; 0 = none), and every thread of the engine process at nice
``pose_nice`` (-10; Linux schedules threads individually), because they share one GIL. A
real-time thread that overruns its frame period (render + estimate, e.g. photo-like optics at
30 fps) sleeps a quarter of its busy time (``vision_rig``; the camera process likewise), so it can
never take a whole core, while a waking pipeline thread preempts the hogs.

Lowering one's nice value needs CAP_SYS_NICE or an RLIMIT_NICE allowance; where the OS refuses,
:func:`raise_thread_priority` says so in one line (the engine raises a ``pose_priority``
warning, as the control process does for its ``control_priority``) and the pipeline runs at
normal priority. Only Linux has per-thread nice values; elsewhere nothing is changed.
"""

from __future__ import annotations

import os
import sys
import threading

#: the nice value the pose pipeline asks for (``SessionConfig.pose_nice``); the robot control
#: process runs at SCHED_FIFO, above every nice value
DEFAULT_POSE_NICE = -10
#: SCHED_FIFO priority of the pose pipeline thread (``SessionConfig.pose_rt_priority``), below
#: the control process's 10
DEFAULT_POSE_RT_PRIORITY = 5


def raise_thread_priority(nice: int) -> str:
    """Give the *calling thread* nice value ``nice`` (< 0 raises its priority); returns one line
    saying what it runs at: ``"nice -10"`` when granted, otherwise ``"normal priority; <why>"``.
    ``nice >= 0``: nothing is changed (``"normal priority (not requested)"``)."""
    nice = int(nice)
    if nice >= 0:
        return "normal priority (not requested)"
    if not sys.platform.startswith("linux") or not hasattr(os, "setpriority"):
        # elsewhere PRIO_PROCESS with a thread id would name a process: never guess
        return f"normal priority; per-thread nice is Linux only (this is {sys.platform})"
    tid = threading.get_native_id()
    try:
        current = os.getpriority(os.PRIO_PROCESS, tid)
        if current <= nice:
            return f"nice {current}"
        os.setpriority(os.PRIO_PROCESS, tid, nice)
        return f"nice {nice}"
    except OSError as exc:
        return f"normal priority; nice {nice} refused ({type(exc).__name__}: {exc.strerror or exc})"


def elevated(priority: str) -> bool:
    """True when a priority answer (:func:`raise_thread_priority`, the robot's
    ``elevate_priority``) means the thread runs above normal."""
    return priority.startswith(("nice -", "SCHED_FIFO"))


def raise_process_priority(nice: int) -> str:
    """Give every thread of this process nice value ``nice`` (threads started later by any of
    them inherit it). One Python process shares one GIL: a pipeline thread at a raised priority
    still waits whenever a normal-priority thread holding the GIL is preempted by CPU load, so
    the whole engine process is raised together. Returns one line, as
    :func:`raise_thread_priority`."""
    nice = int(nice)
    if nice >= 0:
        return "normal priority (not requested)"
    if not sys.platform.startswith("linux") or not hasattr(os, "setpriority"):
        return f"normal priority; per-thread nice is Linux only (this is {sys.platform})"
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError as exc:
        return f"normal priority; cannot list this process's threads ({exc.strerror or exc})"
    refused = None
    for tid in tids:
        try:
            if os.getpriority(os.PRIO_PROCESS, tid) > nice:
                os.setpriority(os.PRIO_PROCESS, tid, nice)
        except ProcessLookupError:
            continue  # a thread that ended meanwhile
        except OSError as exc:
            refused = exc
            break
    if refused is not None:
        return f"normal priority; nice {nice} refused ({type(refused).__name__}: {refused.strerror or refused})"
    return f"nice {nice}"



def raise_pipeline_priority(rt_priority: int, nice: int) -> str:
    """The calling pose-pipeline thread: SCHED_FIFO ``rt_priority`` where the OS allows (else nice
    ``nice`` when that is < 0, else normal: the robot's ``elevate_priority``, one line saying
    which and why); with ``rt_priority`` 0 only the nice value ``nice`` (:func:`raise_thread_priority`)."""
    if int(rt_priority) > 0:
        from monotracker.robot.control_process import elevate_priority

        return elevate_priority(int(rt_priority), fallback_nice=int(nice))
    return raise_thread_priority(nice)


#: the GIL switch interval while a real-time pose pipeline runs in the process (s; Python's 5 ms)
GIL_SWITCH_INTERVAL_S = 0.001


def set_gil_switch_interval(interval_s: float = GIL_SWITCH_INTERVAL_S) -> float:
    """Lower the interpreter's GIL switch interval to ``interval_s`` (never raise it); returns it.

    Detection and registration release the GIL in every OpenCV/NumPy call; each time another
    thread (web server, overlay) takes it, the pipeline thread waits up to the switch interval to
    get it back, dozens of times per frame. At 1 ms instead of 5 ms a frame's estimate on a
    loaded machine stays close to its CPU time (``benchmarks/pose_latency.py``)."""
    import sys as _sys

    if _sys.getswitchinterval() > interval_s:
        _sys.setswitchinterval(interval_s)
    return _sys.getswitchinterval()
