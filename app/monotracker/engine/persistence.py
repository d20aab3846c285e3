"""Crash-safe files: atomic JSON writes (temp file, fsync, rename, fsync of the folder).

A reader (or a restart after ``kill -9``) sees either the previous complete file or the new
complete file, never a torn one: the new content goes to a temporary file in the same folder,
is flushed and fsync'ed, then ``os.replace`` swaps it in (atomic on POSIX), and the folder is
fsync'ed so the rename itself survives a power cut.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically and durably."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    try:
        dfd = os.open(path.parent, os.O_RDONLY)
    except OSError:  # some platforms cannot open folders; the rename is still atomic
        return
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


def atomic_write_json(path: Path, obj) -> None:
    """``json.dumps(obj, indent=1)`` written with :func:`atomic_write_text`."""
    atomic_write_text(path, json.dumps(obj, indent=1, sort_keys=True) + "\n")


def read_json(path: Path):
    """Parsed JSON of ``path``; raises ``OSError`` / ``ValueError`` as json does."""
    with open(path, encoding="utf-8") as fh:
        return json.load(fh)
