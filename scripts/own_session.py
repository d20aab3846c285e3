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

Usage: ``python scripts/own_session.py COMMAND [ARG ...]``
"""

from __future__ import annotations

import ctypes
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


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the launcher dies (Linux only; elsewhere nothing)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def _signal_group(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except ProcessLookupError:
        pass


def run(cmd: list[str]) -> int:
    """Run ``cmd`` in a new session; its exit status (128 + n when it died of signal n)."""
    caller = os.getppid()
    try:
        child = subprocess.Popen(cmd, start_new_session=True, preexec_fn=_die_with_parent)
    except OSError as exc:
        print(f"own_session: cannot run {cmd[0]!r}: {exc.strerror or exc}", file=sys.stderr)
        return 127
    received: list[int] = []

    def forward(sig, _frame):
        received.append(sig)
        _signal_group(child.pid, sig)

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, forward)

    def watch_caller():
        while child.poll() is None:
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
    args = sys.argv[1:] if argv is None else argv
    if not args:
        print("usage: own_session.py COMMAND [ARG ...]", file=sys.stderr)
        return 2
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
