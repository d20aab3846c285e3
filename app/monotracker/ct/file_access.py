"""Whether MonoTracker may read a CT file or folder, and one line saying what to do when not.

A file the process may not read is otherwise reported by what fails next (ITK: "not a
recognised volume", a NIfTI check: "truncated or corrupt", ``Path.exists``: "no such file"),
which sends the operator after the wrong problem. Root reads everything, so these checks only
ever refuse for an ordinary user.
"""

from __future__ import annotations

import os
from pathlib import Path

from monotracker.errors import InputError


def _who(uid: int) -> str:
    try:
        import pwd

        return pwd.getpwuid(uid).pw_name
    except (ImportError, KeyError):
        return str(uid)


def permission_error(path: Path, folder: bool | None = None) -> InputError:
    """The one-line refusal for ``path`` that this process may not read: its owner and mode,
    the user MonoTracker runs as, and what to do."""
    path = Path(path)
    try:
        st = os.stat(path)
        is_dir = os.path.isdir(path) if folder is None else folder
        owner = f"owner {_who(st.st_uid)}, mode {st.st_mode & 0o777:04o}"
    except OSError:  # the folder above it is closed to us
        is_dir = bool(folder)
        owner = f"its folder {path.parent} cannot be entered"
    what = "folder" if is_dir else "file"
    me = _who(os.geteuid()) if hasattr(os, "geteuid") else "this user"
    return InputError(f"cannot read the {what} {path}: permission denied ({owner}; MonoTracker runs as {me}): "
                      f"give {me} read access to it (chmod / chown, or ask its owner) or copy it somewhere {me} can read")


def check_readable(path: Path) -> None:
    """Raise the :func:`permission_error` line when ``path`` (file or folder) exists but cannot
    be read (a folder: listed and entered); a missing path raises ``no such file or folder``."""
    path = Path(path)
    try:
        os.stat(path)
    except FileNotFoundError:
        raise InputError(f"no such file or folder: {path}") from None
    except PermissionError:
        raise permission_error(path) from None
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror or exc}") from None
    mode = os.R_OK | (os.X_OK if path.is_dir() else 0)
    if not os.access(path, mode):
        raise permission_error(path)
