"""What the load benchmarks share: CPU hogs beside the app, and a session folder with a plan.

``hogs(n)`` (a context manager) runs ``n`` busy loops at nice 0, whatever priority this process
has, each tagged ``hog-monotracker-bench`` and ending by itself when this script is gone; they
are killed on exit. ``planned_home(prefix)``: a new session folder with the phantom's fiducials
confirmed and the sample path planned (a simulated-clock session made it)."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

#: a busy loop at nice 0 that ends when its parent (the benchmark) is gone
HOG = ("import os\nos.setpriority(os.PRIO_PROCESS, 0, 0)\nparent = os.getppid()\n"
       "while os.getppid() == parent:\n    for _ in range(1000000):\n        pass\n")


def start_hogs(n: int) -> list[subprocess.Popen]:
    """``n`` busy loops at normal priority (nice 0 whatever ours is), tagged so that only ours are
    ever killed."""
    return [subprocess.Popen([sys.executable, "-c", HOG, "hog-monotracker-bench"]) for _ in range(n)]


def stop_hogs(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
    for p in procs:
        p.wait(10)


@contextmanager
def hogs(n: int):
    """``n`` CPU hogs for the duration of the ``with`` block."""
    procs = start_hogs(n)
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
