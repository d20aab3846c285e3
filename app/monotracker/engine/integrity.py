"""Content hashes that let a saved session prove it was not changed behind the app's back.

* :func:`stamp_plan_dict` adds ``integrity.plan_sha256`` to a plan's dict: SHA-256 of its
  canonical JSON (sorted keys, no whitespace) without that one key. :func:`plan_stamp_problem`
  recomputes it on the parsed file: an edit made outside the app (a moved fiducial, a target, a
  hand-eye) no longer matches. JSON floats round-trip exactly, so an untouched file always matches.
* :func:`content_sha256` hashes a file's bytes, or a folder's files (a DICOM series: relative
  names and contents, in sorted order); the plan records it for its CT and calibration file, and a
  restart compares them.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

_CHUNK = 1 << 20


def _canonical(d: dict) -> bytes:
    return json.dumps(d, sort_keys=True, separators=(",", ":"), allow_nan=True).encode("utf-8")


def plan_content_sha256(d: dict) -> str:
    """SHA-256 (hex) of a plan dict without ``integrity.plan_sha256``."""
    body = dict(d)
    integ = body.get("integrity")
    if isinstance(integ, dict):
        body["integrity"] = {k: v for k, v in integ.items() if k != "plan_sha256"}
    return hashlib.sha256(_canonical(body)).hexdigest()


def stamp_plan_dict(d: dict) -> dict:
    """``d`` with ``integrity.plan_sha256`` set to its content hash (``d`` is modified and returned)."""
    integ = dict(d.get("integrity") or {})
    integ.pop("plan_sha256", None)
    d["integrity"] = integ
    integ["plan_sha256"] = plan_content_sha256(d)
    return d


def plan_stamp_problem(d: dict) -> str | None:
    """None when the parsed plan file carries a content hash that matches; else one line."""
    integ = d.get("integrity") if isinstance(d, dict) else None
    rec = integ.get("plan_sha256") if isinstance(integ, dict) else None
    if not isinstance(rec, str):
        return "the plan file carries no content hash (written by an older version or by hand)"
    if rec != plan_content_sha256(d):
        return "the plan file was changed outside the app (its content hash does not match)"
    return None


def content_sha256(path) -> str:
    """SHA-256 (hex) of a file's bytes, or of a folder's regular files (names relative to the
    folder and contents, sorted by name). Raises ``OSError`` when it cannot be read."""
    p = Path(path)
    h = hashlib.sha256()
    if p.is_dir():
        files = sorted(q for q in p.rglob("*") if q.is_file())
        for q in files:
            h.update(str(q.relative_to(p)).encode("utf-8") + b"\0")
            _feed(h, q)
            h.update(b"\0")
    else:
        _feed(h, p)
    return h.hexdigest()


def _feed(h, path: Path) -> None:
    with open(path, "rb") as fh:
        while True:
            b = fh.read(_CHUNK)
            if not b:
                return
            h.update(b)


def compare_content(path, recorded: str | None, what: str) -> str | None:
    """None when ``path`` still hashes to ``recorded`` (or nothing was recorded); else one line."""
    if not recorded:
        return None
    if path is None:
        return f"the plan's {what} path is not recorded"
    try:
        now = content_sha256(path)
    except OSError as exc:
        return f"the plan's {what} {path} cannot be read ({exc.strerror or exc})"
    if now != recorded:
        return f"the plan's {what} {path} changed since the plan was made (content hash differs)"
    return None
