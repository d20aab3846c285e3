"""What the load benchmarks share: CPU hogs beside the app, and a session folder with a plan.

``hogs(n)`` (a context manager) runs ``n`` busy loops at nice 0, whatever priority this process
has, each tagged ``hog-monotracker-bench`` and ending by itself when this script is gone; they
are killed on exit. By default (``own_session=True``) the ``n`` loops run together in a process
session of their own, as a neighbour's load does (issue 29's "4 CPU hogs beside them": another
user's job, a build): on a kernel with autogroup scheduling (``/proc/sys/kernel/sched_autogroup_enabled``)
the CPU is shared between sessions first, so the app keeps its session's share (half the machine
beside one busy session) whatever number of loops the neighbour runs. ``own_session=False`` is the
old behaviour: the loops in this process's session and autogroup, competing with the app thread by
thread (with 4 loops on 2 cores the app's threads got a tiny share: issue 33); the tests'
``MONOTRACKER_TEST_HOGS`` (``tests/conftest.py``) and ``benchmarks/live_step_cpu.py`` keep it, to
load the app harder than a neighbour would. ``planned_home(prefix)``: a new session folder with
the phantom's fiducials confirmed and the sample path planned (a simulated-clock session made it)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

#: a busy loop at nice 0 that ends when its parent (the benchmark) is gone
HOG = ("import os\nos.setpriority(os.PRIO_PROCESS, 0, 0)\nparent = os.getppid()\n"
       "while os.getppid() == parent:\n    for _ in range(1000000):\n        pass\n")

#: ``n`` busy loops at nice 0 in one new session (``argv[1]``: n, ``argv[2]``: the benchmark's pid):
#: the session's leader forks the loops, waits, and on SIGTERM (or when the benchmark is gone) kills
#: and reaps them (left to init, killed loops would stay as zombies); each loop also ends when the
#: benchmark is gone
HOG_SESSION = """import os, signal, sys, time
os.setpriority(os.PRIO_PROCESS, 0, 0)
n, bench = int(sys.argv[1]), int(sys.argv[2])
def alive():
    try:
        os.kill(bench, 0)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
kids = []
for _ in range(n):
    pid = os.fork()
    if pid == 0:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        while alive():
            for _ in range(1000000):
                pass
        os._exit(0)
    kids.append(pid)
def end(*_):
    for k in kids:
        try:
            os.kill(k, signal.SIGKILL)
        except ProcessLookupError:
            pass
    for k in kids:
        try:
            os.waitpid(k, 0)
        except ChildProcessError:
            pass
    os._exit(0)
signal.signal(signal.SIGTERM, end)
while alive():
    time.sleep(0.5)
end()
"""


def start_hogs(n: int, own_session: bool = True) -> list[subprocess.Popen]:
    """``n`` busy loops at normal priority (nice 0 whatever ours is), tagged so that only ours are
    ever killed. ``own_session`` (see the module docstring): True, one process leading a new
    session that holds the ``n`` loops (the list has that leader; :func:`stop_hogs` ends them
    all); False, ``n`` processes in this process's session."""
    if n <= 0:
        return []
    if own_session:
        return [subprocess.Popen([sys.executable, "-c", HOG_SESSION, str(n), str(os.getpid()), "hog-monotracker-bench"],
                                 start_new_session=True)]
    return [subprocess.Popen([sys.executable, "-c", HOG, "hog-monotracker-bench"]) for _ in range(n)]


def stop_hogs(procs: list[subprocess.Popen]) -> None:
    """Kill the hogs of :func:`start_hogs` (a session's leader kills and reaps its loops)."""
    leaders = []
    for p in procs:
        try:
            if os.getsid(p.pid) == p.pid:     # a session of hogs: its leader ends its loops
                leaders.append(p)
                p.terminate()
                continue
        except (ProcessLookupError, PermissionError):
            pass
        p.kill()
    for p in procs:
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)
    for p in leaders:      # anything of a session left over (a leader that did not end them)
        try:
            os.killpg(p.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass


@contextmanager
def hogs(n: int, own_session: bool = True):
    """``n`` CPU hogs for the duration of the ``with`` block (``own_session``: see
    :func:`start_hogs`)."""
    procs = start_hogs(n, own_session)
    try:
        yield procs
    finally:
        stop_hogs(procs)


def planned_home(prefix: str) -> Path:
    """A session folder with a confirmed plan (the phantom's fiducials, the sample path)."""
    from monotracker.engine import Session, SessionConfig
    from monotracker.sim.phantom import default_phantom

    home = Path(tempfile.mkdtemp(prefix=prefix))
    s = Session(SessionConfig(home=home, clock="sim"))
    try:
        ph = default_phantom()
        for c in ph.fiducial_centres_lps:
            assert s.add_fiducial(c, ph.fiducial_radius_mm).ok
        assert s.confirm_fiducials().ok
        assert s.use_sample_plan().ok
    finally:
        s.shutdown()
    return home
