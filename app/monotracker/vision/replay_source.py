"""A session recording as a frame source (``--camera replay:DIR``), and the recording's file layout.

A recording folder (written by :mod:`monotracker.engine.recording`; the layout is documented in
``docs/interop.md``) holds ``manifest.json`` and one JSON-lines stream per kind. This module reads
the part a camera needs: ``frames.jsonl`` (one row per frame: ``seq``, ``index``, ``t_capture`` s,
``segment``, ``kind`` ``"image"``, ``file`` ``frames/NNNNNN.png``, ``sha256`` of the PNG bytes) and
the lossless PNG images. Point-level recordings (``kind`` ``"points"``, from the ``sim-points``
camera) have no images and are refused as a camera source.

A recording is read only when it is complete and intact: the manifest says ``complete: true`` (it
is rewritten so only when the recording was closed) or ``truncated: true`` (a full disk stopped it;
every stream was cut back to the last whole frame, which is where the replay ends), the frame
count matches, every PNG exists and matches its checksum. Anything else raises :class:`InputError` with one line saying what is wrong,
never a partial or silently different stream.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import cv2
import numpy as np

from monotracker.errors import InputError, MonoTrackerError

from .frames import Frame, FrameSource

FORMAT = "monotracker-recording"
VERSION = 1
MANIFEST = "manifest.json"
FRAMES = "frames.jsonl"
FRAMES_DIR = "frames"


def read_jsonl(path: Path) -> list[dict]:
    """Rows of a JSON-lines file; :class:`InputError` naming the file and line if one is broken."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"recording is incomplete: {path.name} is missing")
    rows = []
    with open(path, encoding="utf-8") as fh:
        for n, line in enumerate(fh, 1):
            if not line.strip():
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                raise InputError(f"recording is corrupt: {path.name} line {n} is not valid JSON "
                                 "(truncated by a crash?)") from None
            if not isinstance(row, dict):
                raise InputError(f"recording is corrupt: {path.name} line {n} is not a JSON object")
            rows.append(row)
    return rows


def read_manifest(folder: str | Path) -> dict:
    """The checked manifest of a closed recording (:class:`InputError` otherwise)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"recording folder not found: {folder}")
    p = folder / MANIFEST
    if not p.is_file():
        raise InputError(f"{folder} is not a MonoTracker recording (no {MANIFEST})")
    try:
        m = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"recording manifest {p} is unreadable ({exc})") from None
    if not isinstance(m, dict) or m.get("format") != FORMAT:
        raise InputError(f"{p} is not a MonoTracker recording manifest")
    if int(m.get("version", -1)) > VERSION:
        raise InputError(f"recording version {m.get('version')} is newer than this program ({VERSION})")
    if not m.get("complete") and not m.get("truncated"):
        raise InputError(f"recording {folder} is incomplete: it was never closed (the session ended "
                         "abnormally while recording)")
    if m.get("frames_dropped"):
        raise InputError(f"recording {folder} is incomplete: {m['frames_dropped']} frames were dropped "
                         "while recording (the disk could not keep up)")
    return m


def read_frame_index(folder: str | Path, manifest: dict | None = None) -> list[dict]:
    """The checked rows of ``frames.jsonl`` (count against the manifest, files present)."""
    folder = Path(folder)
    m = manifest if manifest is not None else read_manifest(folder)
    rows = read_jsonl(folder / FRAMES)
    want = int(m.get("frames", -1))
    if len(rows) != want:
        raise InputError(f"recording {folder} is incomplete: manifest lists {want} frames, {FRAMES} has {len(rows)}")
    for r in rows:
        for key in ("seq", "index", "t_capture", "segment", "kind"):
            if key not in r:
                raise InputError(f"recording is corrupt: a row of {FRAMES} lacks {key!r}")
        if r["kind"] == "image" and not (folder / str(r.get("file", ""))).is_file():
            raise InputError(f"recording is incomplete: frame file {r.get('file')} is missing")
    return rows


def load_frame_image(folder: Path, row: dict, verify: bool = True) -> np.ndarray:
    """The BGR image of one ``kind == "image"`` frame row, checked against its sha256."""
    p = Path(folder) / str(row["file"])
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise InputError(f"recording frame {p.name} is unreadable ({exc})") from None
    if verify and row.get("sha256") and hashlib.sha256(data).hexdigest() != row["sha256"]:
        raise InputError(f"recording frame {p.name} is corrupt (checksum mismatch)")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(f"recording frame {p.name} is corrupt (not a readable PNG)")
    return img


class ReplaySource(FrameSource):
    """The frames of a closed recording, in order. ``realtime``: pace reads by the recorded
    capture intervals (a live-like camera); else as fast as read. ``keep_timestamps``: frames carry
    the recorded ``t_capture`` and ``index`` (offline replay); else ``time.monotonic()`` at read and
    a running index, like any camera. ``read()`` returns None at the end."""

    def __init__(self, folder: str | Path, realtime: bool = False, keep_timestamps: bool = False,
                 verify: bool = True):
        super().__init__()
        self.folder = Path(folder)
        self.name = f"recording {self.folder.name}"
        self.manifest = read_manifest(self.folder)
        self.rows = read_frame_index(self.folder, self.manifest)
        if any(r["kind"] != "image" for r in self.rows):
            raise InputError(f"recording {self.folder} holds detected points, not images: replay it with "
                             "`monotracker replay`, it cannot be a camera")
        if not self.rows:
            raise InputError(f"recording {self.folder} holds no frames")
        self.realtime, self.keep_timestamps, self.verify = bool(realtime), bool(keep_timestamps), bool(verify)
        self._next = 0
        self._t0_wall = None
        self.row: dict | None = None  # the row of the frame last read

    def __len__(self) -> int:
        return len(self.rows)

    def read(self) -> Frame | None:
        if self._closed:
            raise MonoTrackerError(f"{self.name}: read() after close()")
        if self._next >= len(self.rows):
            return None
        row = self.rows[self._next]
        self._next += 1
        if self.realtime:
            t_rec = float(row["t_capture"]) - float(self.rows[0]["t_capture"])
            if self._t0_wall is None:
                self._t0_wall = time.monotonic()
            wait = self._t0_wall + t_rec - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        img = load_frame_image(self.folder, row, self.verify)
        self.row = row
        if self.keep_timestamps:
            return Frame(img, float(row["t_capture"]), int(row["index"]))
        f = Frame(img, time.monotonic(), self._index)
        self._index += 1
        return f

    def _read_image(self):  # read() is overridden; kept for the base-class contract
        raise NotImplementedError


def calibration_path(folder: str | Path) -> Path:
    """The camera calibration a recording ran on (``calibration.json``, vision's JSON format)."""
    return Path(folder) / "calibration.json"
