"""One session per folder: the running session holds an exclusive lock on its session folder.

Two servers (or a server and the headless demo) on one folder would append to the same audit
log and restore and overwrite each other's plan (issue 34). :class:`SessionFolderLock` takes an
advisory ``flock`` on ``<folder>/session.lock`` for as long as the session runs and writes who
holds it (pid, host, user, since) into that file; a second session on the folder is refused with
one line naming the holder (:class:`SessionFolderBusy`).

The operating system drops the lock when its process ends, however it ends (``kill -9``, a
crash, a power cut): a lock left by a dead process never blocks the next session. Its holder
line stays in the file (it is only cleared on a clean release), so the next session can say
whose lock it took over (:attr:`SessionFolderLock.took_over`), and the audit log records it.

Why ``fcntl.flock`` and no library: it is the standard library's interface to the kernel's own
lock, which is what makes a killed holder's lock disappear; a lock *file* that is created and
deleted (``filelock``'s soft mode, pid files) leaves stale locks behind and races on deletion.
The file is never deleted (deleting a locked file lets a third process lock a new file of the
same name beside it). Limits: POSIX only (elsewhere the folder is not locked and
:attr:`SessionFolderLock.note` says so); on network file systems ``flock`` may be local to one
machine, so a folder shared between machines is not protected.
"""

from __future__ import annotations

import getpass
import json
import os
import socket
import time
import weakref
from pathlib import Path

from monotracker.errors import InputError

LOCK_FILE = "session.lock"


class SessionFolderBusy(InputError):
    """Another running session holds the folder (the message names it, one line)."""


def _holder_line(info: dict | None) -> str:
    if not info:
        return "another MonoTracker session (holder not recorded yet)"
    since = info.get("since_iso") or "?"
    return (f"MonoTracker pid {info.get('pid', '?')} on host {info.get('host', '?')} "
            f"(user {info.get('user', '?')}, since {since})")


class SessionFolderLock:
    """The exclusive lock on one session folder. :meth:`acquire` takes it or raises
    :class:`SessionFolderBusy`; :meth:`release` gives it back (idempotent)."""

    def __init__(self, folder):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_FILE
        self._fd: int | None = None
        #: the holder whose lock was left behind (its process ended without releasing it), or None
        self.took_over: dict | None = None
        #: why the folder could not be locked at all ("" when it is locked)
        self.note = ""

    @property
    def held(self) -> bool:
        return self._fd is not None

    def read_holder(self) -> dict | None:
        """What the lock file says about its (last) holder, or None (empty or unreadable)."""
        try:
            text = self.path.read_text(encoding="utf-8").strip()
            return json.loads(text) if text else None
        except (OSError, ValueError):
            return None

    def acquire(self) -> "SessionFolderLock":
        """Take the lock (returns self). Raises :class:`SessionFolderBusy` naming the holder when
        another process holds it. A folder where no lock file can be made (read-only) is used
        unlocked (:attr:`note` says why; nothing can be written there by anyone then)."""
        try:
            import fcntl
        except ImportError:  # not POSIX
            self.note = "session folder not locked (no flock on this system)"
            return self
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError:
            try:
                fd = os.open(self.path, os.O_RDONLY)
            except OSError as exc:
                self.note = f"session folder not locked ({exc.strerror or exc})"
                return self
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise SessionFolderBusy(f"session folder {self.folder} is in use by {_holder_line(self.read_holder())}; "
                                    "stop that one first or choose another folder (--home)") from None
        previous = self.read_holder()
        if previous:
            self.took_over = previous  # a clean release empties the file: its holder ended without one
        info = {"pid": os.getpid(), "host": socket.gethostname(), "user": _user(),
                "since": time.time(), "since_iso": time.strftime("%Y-%m-%d %H:%M:%S %Z")}
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(info) + "\n").encode("utf-8"), 0)
        except OSError:
            pass  # read-only lock file: locked, holder not recorded
        self._fd = fd
        # a holder dropped without release() (its owner failed half-way through starting) lets go
        # when it is collected; a process that ends lets go in any case
        self._finalizer = weakref.finalize(self, _close, fd, False)
        return self

    def release(self) -> None:
        """Clear the holder line and drop the lock (idempotent; never raises)."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        self._finalizer.detach()
        _close(fd, True)


def _close(fd: int, clear: bool) -> None:
    """Clear the holder line (a clean release) and close ``fd``, which drops the flock."""
    if clear:
        try:
            os.ftruncate(fd, 0)
        except OSError:
            pass
    try:
        os.close(fd)
    except OSError:
        pass


def _user() -> str:
    try:
        return getpass.getuser()
    except Exception:  # noqa: BLE001 - no name for this uid
        return f"uid {os.getuid()}" if hasattr(os, "getuid") else "?"
