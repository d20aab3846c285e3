"""Run a command in a session of its own and return its exit status (``scripts/test.sh`` runs
each part of the test suite through it).

Why: with the kernel's autogroup scheduler on (``/proc/sys/kernel/sched_autogroup_enabled`` = 1,
the default of Debian's and Ubuntu's kernels) the CPU is shared between sessions first and only
then between the threads of a session. A test run started from a shell competes thread by
thread with everything else that shell's session runs (a build, CPU hogs started beside it),
while the app it serves, the browser (Playwright starts chromium in a session of its own) and a
deployed MonoTracker service each get a session's share. Measured (issue 35, docs/performance.md
"Tests under load"): the end-to-end browser test beside 4 busy loops started from the same shell,
5 runs each way: 56-160 s (median 110) with 2-14 % of its poses over the engine's 150 ms limit in
the shell's session; in a session of its own 53-83 s (median 69) and 3-8 %. Nothing changes
where the autogroup scheduler is off or where the other load runs in other sessions already.

What a session of its own must not cost: Ctrl-C, ``kill`` and a closed terminal still stop the
run. SIGINT, SIGTERM and SIGHUP sent to this launcher are passed on to the command's whole
process group; after an interrupt the launcher ends by the same signal, so that the calling
script stops too. The command is also stopped (SIGTERM, then SIGKILL after
:data:`GRACE_S`) when the process that started this launcher dies, and gets SIGTERM from the
kernel if this launcher is killed outright (``PR_SET_PDEATHSIG``).

``--nice N`` runs the command's session (its autogroup) at niceness N, ``--while PID`` only until
process PID has ended: ``scripts/test.sh`` runs the parallel part of the suite at 19 while the
serial lane runs beside it, so that it takes only what the serial lane leaves idle, then at the
normal weight again (beside CPU hogs a session at 19 would get almost nothing); also, at once, if
the lowered session got under :data:`STARVED_SHARE` of a core for :data:`STARVED_S` seconds (other
load came: its tests' own waits must not run out while it is starved).

Usage: ``python scripts/own_session.py [--nice N [--while PID]] COMMAND [ARG ...]``
"""

from __future__ import annotations

import ctypes
import errno
import os
import signal
import subprocess
import sys
import threading
import time

#: seconds between SIGTERM and SIGKILL when the caller has died
GRACE_S = 10.0
#: seconds between checks that the caller is still alive
POLL_S = 1.0
_PR_SET_PDEATHSIG = 1
#: a lowered session that got less than :data:`STARVED_SHARE` of a core over the last
#: :data:`STARVED_S` seconds is starved by other load (its low weight takes only idle CPU, and there
#: is none): it gets its normal weight back at once, so that its tests' own waits do not run out
#: (a session that used that little because it was idle gets it back too: no harm). The tests set
#: a shorter window with OWN_SESSION_STARVED_S.
STARVED_S = float(os.environ.get("OWN_SESSION_STARVED_S", "20"))
STARVED_SHARE = 0.05


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the launcher dies (Linux only; elsewhere nothing)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def autogroup_nice(pid: int | str = "self") -> int | None:
    """The niceness of ``pid``'s autogroup (the kernel shares the CPU between autogroups first, by
    their weight; a session is one autogroup), or None where the kernel has none."""
    try:
        with open(f"/proc/{pid}/autogroup") as f:
            return int(f.read().split()[-1])
    except (OSError, ValueError, IndexError):
        return None


def set_autogroup_nice(pid: int | str, nice: int, tries: int = 60) -> bool:
    """Set ``pid``'s autogroup (its whole session) to niceness ``nice``: weight 15 at 19 against a
    nice-0 group's 1024, so a session at 19 takes almost only what the other sessions leave idle.
    Raising it, or lowering it back to 0 or more, needs no privilege; the kernel takes such a
    change at most every 0.1 s from an unprivileged caller (EAGAIN: tried again). False where the
    kernel has no autogroups or refused."""
    for _ in range(tries):
        try:
            with open(f"/proc/{pid}/autogroup", "w") as f:
                f.write(str(nice))
            return True
        except OSError as exc:
            if exc.errno != errno.EAGAIN:
                return False
            time.sleep(0.05)
    return False


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:   # a zombie has ended
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[-1].split()[0] != "Z"
    except OSError:
        return True


def session_cpu_s(sid: int) -> float:
    """CPU seconds used so far by the processes of session ``sid`` and the children they reaped
    (from /proc; a process that ended unreaped drops out, so the sum can step down)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as f:
                fields = f.read().rsplit(")", 1)[-1].split()
        except OSError:
            continue
        if len(fields) > 14 and int(fields[3]) == sid:     # fields after the name: state, ppid, pgrp, session, ...
            total += sum(int(x) for x in fields[11:15])    # utime, stime, cutime, cstime
    return total / tick


def _signal_group(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except ProcessLookupError:
        pass


def run(cmd: list[str], nice: int = 0, while_pid: int | None = None) -> int:
    """Run ``cmd`` in a new session; its exit status (128 + n when it died of signal n). With
    ``nice`` > 0 the new session's autogroup runs at that niceness (:func:`set_autogroup_nice`;
    the processes' own niceness is left alone, so it can be undone without privilege), until
    process ``while_pid`` has ended if given (checked every :data:`POLL_S`), then at this
    launcher's own autogroup niceness again."""
    caller = os.getppid()
    normal = autogroup_nice()

    def in_child():   # after the new session is made (subprocess calls setsid() first)
        _die_with_parent()
        if nice > 0:
            set_autogroup_nice("self", nice)

    try:
        child = subprocess.Popen(cmd, start_new_session=True, preexec_fn=in_child)
    except OSError as exc:
        print(f"own_session: cannot run {cmd[0]!r}: {exc.strerror or exc}", file=sys.stderr)
        return 127
    received: list[int] = []

    def forward(sig, _frame):
        received.append(sig)
        _signal_group(child.pid, sig)

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, forward)

    lowered = nice > 0 and while_pid is not None and normal is not None

    def give_weight_back(why: str) -> None:
        nonlocal lowered
        lowered = False
        if why:
            print(f"own_session: {why}: the command's session back to its normal weight", file=sys.stderr)
        if not set_autogroup_nice(child.pid, max(normal, 0)):
            print(f"own_session: could not set the command's priority back to {max(normal, 0)}", file=sys.stderr)

    def watch_caller():
        used: list[tuple[float, float]] = []   # (monotonic s, the session's CPU s) while lowered
        while child.poll() is None:
            if lowered and not _alive(while_pid):   # its time beside that process is over
                give_weight_back("")
            elif lowered:
                now = time.monotonic()
                used.append((now, session_cpu_s(child.pid)))
                while used and used[0][0] < now - STARVED_S:
                    used.pop(0)
                t0, c0 = used[0]
                if now - t0 >= STARVED_S - 2 * POLL_S and used[-1][1] - c0 < STARVED_SHARE * (now - t0):
                    give_weight_back(f"under {STARVED_SHARE:.0%} of a core for {now - t0:.0f} s beside other load")
            if os.getppid() != caller:      # re-parented: whoever started us is gone
                _signal_group(child.pid, signal.SIGTERM)
                try:
                    child.wait(GRACE_S)
                except subprocess.TimeoutExpired:
                    _signal_group(child.pid, signal.SIGKILL)
                return
            time.sleep(POLL_S)

    threading.Thread(target=watch_caller, name="own-session-watch", daemon=True).start()
    rc = child.wait()
    if received:
        sig = received[0]
        signal.signal(sig, signal.SIG_DFL)
        os.kill(os.getpid(), sig)       # end as the caller's shell expects of an interrupted job
    return rc if rc >= 0 else 128 - rc


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    nice, while_pid = 0, None
    try:
        if args[:1] == ["--nice"]:
            nice = int(args[1])
            args = args[2:] if 0 <= nice <= 19 else []
        if args[:1] == ["--while"]:
            while_pid = int(args[1])
            args = args[2:] if while_pid > 0 and nice > 0 else []
    except (IndexError, ValueError):
        args = []
    if not args:
        print("usage: own_session.py [--nice 0-19 [--while PID]] COMMAND [ARG ...]", file=sys.stderr)
        return 2
    return run(args, nice, while_pid)


if __name__ == "__main__":
    sys.exit(main())
