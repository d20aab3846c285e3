"""``scripts/own_session.py``: scripts/test.sh runs each part of the suite in a session of its own
(the kernel's autogroup scheduler then shares the CPU between it and whatever the caller's session
runs); Ctrl-C, kill and a dead caller must still stop it. Every wait is on a file or a process
state, with a generous bound."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAUNCHER = ROOT / "scripts" / "own_session.py"

#: the command under the launcher: writes its session id and pid, starts a grandchild in its own
#: process group's session, then waits; it writes "INT" when interrupted.
CHILD = r"""
import os, signal, subprocess, sys, time
out = sys.argv[1]
gc = subprocess.Popen([sys.executable, "-c", "import time\nwhile True: time.sleep(0.2)"])
def on_int(sig, frame):
    open(out + ".int", "w").write("INT")
    gc.terminate(); gc.wait()
    sys.exit(130)
signal.signal(signal.SIGINT, on_int)
open(out + ".tmp", "w").write(f"{os.getsid(0)} {os.getpid()} {gc.pid}")
os.replace(out + ".tmp", out)
while True:
    time.sleep(0.2)
"""


def _wait_for(pred, what: str, bound_s: float = 60.0):
    end = time.monotonic() + bound_s
    while time.monotonic() < end:
        if pred():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (exited, not yet reaped by its parent) counts as gone
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def _start(tmp_path, *wrap):
    out = tmp_path / "child.txt"
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    cmd = [*wrap, sys.executable, str(LAUNCHER), sys.executable, str(script), str(out)]
    p = subprocess.Popen(cmd)
    _wait_for(out.exists, "the command to start")
    sid, pid, gc = (int(x) for x in out.read_text().split())
    return p, out, sid, pid, gc


def test_exit_status_passes_through_and_a_missing_command_is_one_line(tmp_path):
    r = subprocess.run([sys.executable, str(LAUNCHER), sys.executable, "-c", "import sys; sys.exit(7)"])
    assert r.returncode == 7
    r = subprocess.run([sys.executable, str(LAUNCHER), str(tmp_path / "no-such-program")],
                       capture_output=True, text=True)
    assert r.returncode == 127
    assert "cannot run" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, str(LAUNCHER)], capture_output=True, text=True)
    assert r.returncode == 2 and "usage" in r.stderr


def test_the_command_runs_in_a_session_of_its_own_and_ctrl_c_stops_it(tmp_path):
    p, out, sid, pid, gc = _start(tmp_path)
    try:
        assert sid == pid != os.getsid(0)          # a new session, led by the command
        assert os.getsid(gc) == sid                # its children stay in it
        p.send_signal(signal.SIGINT)               # as the terminal's Ctrl-C reaches the launcher
        _wait_for(lambda: p.poll() is not None, "the launcher to end")
        assert (tmp_path / "child.txt.int").read_text() == "INT"   # the command got the interrupt
        assert p.returncode == -signal.SIGINT      # and the launcher ends as an interrupted job
        _wait_for(lambda: not _alive(pid) and not _alive(gc), "the command and its child to end")
    finally:
        for q in (pid, gc):
            if _alive(q):
                os.kill(q, signal.SIGKILL)


def test_sigterm_reaches_the_whole_group(tmp_path):
    p, out, sid, pid, gc = _start(tmp_path)
    try:
        p.terminate()
        _wait_for(lambda: p.poll() is not None, "the launcher to end")
        assert p.returncode == -signal.SIGTERM
        _wait_for(lambda: not _alive(pid) and not _alive(gc), "the command and its child to end")
    finally:
        for q in (pid, gc):
            if _alive(q):
                os.kill(q, signal.SIGKILL)


def _ppid(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[1])


@pytest.mark.parametrize("victim", ["caller", "launcher"])
def test_the_command_is_stopped_when_its_caller_or_the_launcher_is_killed(tmp_path, victim):
    # a shell that stays between us and the launcher plays the caller (scripts/test.sh). SIGKILL
    # cannot be forwarded: the launcher notices that its caller is gone and stops the command's
    # group, or (the launcher itself killed) the kernel's parent-death signal stops the command
    p, out, sid, pid, gc = _start(tmp_path, "bash", "-c", '"$@"; exit $?', "bash")
    launcher = _ppid(pid)
    assert _ppid(launcher) == p.pid
    try:
        os.kill(p.pid if victim == "caller" else launcher, signal.SIGKILL)
        _wait_for(lambda: not _alive(pid), "the command to end")
        if victim == "caller":
            _wait_for(lambda: not _alive(gc), "the command's child to end")
            _wait_for(lambda: not _alive(launcher), "the launcher to end")
    finally:
        p.wait(30)
        for q in (pid, gc):
            if _alive(q):
                os.kill(q, signal.SIGKILL)



#: the command under ``--nice``: rewrites its file every 50 ms with its session id, its own
#: niceness and its autogroup's niceness
SHOW_PRIORITY = r"""
import os, sys, time
out = sys.argv[1]
while True:
    group = open("/proc/self/autogroup").read().split()[-1]
    open(out + ".tmp", "w").write(f"{os.getsid(0)} {os.getpid()} {os.getpriority(os.PRIO_PROCESS, 0)} {group}")
    os.replace(out + ".tmp", out)
    open(out + ".log", "a").write(group + "\n")   # every reading, in order
    time.sleep(0.05)
"""


def _read_priority(out):
    try:
        return tuple(int(x) for x in out.read_text().split())
    except (OSError, ValueError):
        return None


@pytest.mark.skipif(not Path("/proc/self/autogroup").exists(), reason="this kernel has no autogroup scheduling "
                    "(scripts/test.sh then runs the two parts one after the other)")
def test_nice_lowers_the_commands_session_while_the_other_process_runs_then_gives_it_back(tmp_path):
    """``--nice 19 --while PID`` (scripts/test.sh's parallel part beside the serial lane): the
    command's session (its autogroup) runs at niceness 19 while process PID lives, then at the
    launcher's own autogroup niceness again; the command's own niceness and the caller's session
    are never touched (so no privilege is needed to give the weight back). Every wait is on the
    command's file."""
    mine = os.getpriority(os.PRIO_PROCESS, 0)
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    script, out = tmp_path / "show.py", tmp_path / "priority.txt"
    script.write_text(SHOW_PRIORITY)
    # the launcher in a session of its own, whose autogroup starts at niceness 0 (the weight it
    # gives back), whatever this test's session runs at (the suite's parallel part: 19 or 0)
    p = subprocess.Popen([sys.executable, str(LAUNCHER), "--nice", "19", "--while", str(other.pid),
                          sys.executable, str(script), str(out)], start_new_session=True)
    try:
        _wait_for(lambda: _read_priority(out) is not None, "the command to start")
        assert int(Path(f"/proc/{p.pid}/autogroup").read_text().split()[-1]) == 0
        sid, pid, nice, group = _read_priority(out)
        assert sid == pid != os.getsid(0) and sid != p.pid
        assert (nice, group) == (mine, 19)
        assert int(Path(f"/proc/{p.pid}/autogroup").read_text().split()[-1]) == 0   # the caller's left alone
        other.kill()
        other.wait()
        _wait_for(lambda: _read_priority(out)[3] == 0, "the session's weight to come back")
        assert _read_priority(out)[2] == mine
    finally:
        for q in (other, p):
            if q.poll() is None:
                q.terminate()
                q.wait()


def test_nice_and_while_need_valid_values():
    for bad in (["--nice"], ["--nice", "x", "true"], ["--nice", "20", "true"], ["--nice", "-5", "true"],
                ["--while", "1", "true"], ["--nice", "19", "--while", "0", "true"], ["--nice", "19", "--while"]):
        r = subprocess.run([sys.executable, str(LAUNCHER), *bad], capture_output=True, text=True)
        assert r.returncode == 2 and "usage" in r.stderr and "Traceback" not in r.stderr, (bad, r.stderr)


@pytest.mark.skipif(not Path("/proc/self/autogroup").exists(), reason="this kernel has no autogroup scheduling "
                    "(scripts/test.sh then runs the two parts one after the other)")
def test_a_lowered_session_that_gets_no_cpu_gets_its_weight_back_early(tmp_path):
    """Load that comes after the start (CPU hogs beside the suite) leaves a session at nice 19
    almost no CPU, and its tests' own waits would run out: a lowered session that used under 5 %
    of a core over the window (``OWN_SESSION_STARVED_S``, 20 s by default; 6 s here) gets its
    normal weight back while process PID still runs, and says so on stderr. The command here
    sleeps (it uses no CPU, as a starved one), so no CPU is burnt to show it."""
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    script, out = tmp_path / "show.py", tmp_path / "priority.txt"
    script.write_text(SHOW_PRIORITY.replace("time.sleep(0.05)", "time.sleep(0.2)"))
    # the command's first reading shows the lowered weight however late the test itself gets to
    # look (a loaded host: the window may be over by then)
    history = Path(str(out) + ".log")
    # the window (6 s) leaves the command's start (a Python start-up, seconds on a loaded host) inside it
    p = subprocess.Popen([sys.executable, str(LAUNCHER), "--nice", "19", "--while", str(other.pid),
                          sys.executable, str(script), str(out)], stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "OWN_SESSION_STARVED_S": "6"}, start_new_session=True)
    try:
        _wait_for(lambda: _read_priority(out) is not None and history.exists(), "the command to start")
        assert int(history.read_text().split()[0]) == 19
        _wait_for(lambda: _read_priority(out)[3] == 0, "the starved session's weight to come back")
        assert other.poll() is None                # the other process still runs
    finally:
        for q in (other, p):
            if q.poll() is None:
                q.terminate()
                q.wait()
    assert "back to its normal weight" in p.stderr.read()
