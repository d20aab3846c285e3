"""Session recording: every estimated camera frame with what the engine made of it, to disk.

:class:`SessionRecorder` attaches to a running :class:`~monotracker.engine.Session` (a pose hook on
the engine loop and an event subscription; ``Session.start_recording(folder)`` does this through
the session's :class:`Recording` part) and writes, timestamped on the session clock (s):

====================  ==========================================================================
``manifest.json``      format, version, program and library versions, session, camera, clock,
                       counts; ``complete: false`` until the recording is closed cleanly
``plan.json``          the plan the session ran on (as ``plan.json`` in the session folder)
``calibration.json``   the camera model (vision's JSON: K px, distortion, image size); a later
                       camera segment with another calibration gets ``calibration-<segment>.json``
``frames/NNNNNN.png``  the frames, lossless PNG, BGR as the detector saw them
``frames.jsonl``       per frame: ``seq``, ``index`` (camera frame index), ``t_capture``,
                       ``segment`` (one per camera start), ``kind`` (``image`` | ``points`` |
                       ``fault``), ``file`` + ``sha256`` (images) or ``points_px`` and ``minor_px`` (sim-points:
                       the balls' centres and image sizes, px),
                       ``camera`` (vision's camera state: ok | frozen | stalled | ...)
``detections.jsonl``   per frame: matched image point per fiducial id (px), status, residual (px)
``poses.jsonl``        per frame: ``ok``, ``trusted``, ``reason``, ``T_cam_ct`` (4x4 mm), FRE,
                       predicted TRE, ``n_matched``, ``t_ready``, ``fault``, simulator truth
``robot.jsonl``        per frame: robot state, joints (rad), needle tip ``T_base_tip`` (mm)
``targets.jsonl``      each new needle target handed to the tracker: ``T_base_target`` (mm), stamp
``alerts.jsonl``       every alert; ``events.jsonl`` every decision/state change (as the audit log)
====================  ==========================================================================

Nothing slow sits on the engine thread: the hook only queues references; a writer thread encodes
PNGs and writes lines. clock="sim" sessions wait for the writer when its queue is full (a complete
recording; the simulated clock does not care); clock="real" sessions never wait: a frame that does
not fit is dropped, counted in the manifest (``frames_dropped``), and the recording is then refused
by replay as incomplete.

A full disk keeps what was written: every stream is flushed after each frame and the offsets of
the last whole frame are kept; when a write fails (``ENOSPC``, a quota, an I/O error) the
recording stops, every stream is cut back to that frame (truncating needs no space), the
partial frame's image is removed, a small reserve file made at the start (:data:`RESERVE_BYTES`)
is deleted to make room, and the manifest is written with ``complete: false``, ``truncated:
true``, the frames kept and the error; ``recording_failed`` says so once. Replay accepts such a
recording up to where it stops. A folder without :data:`MIN_FREE_BYTES` free is refused at the
start with one line.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import math
import os
import queue
import shutil
import threading
from pathlib import Path

import cv2
import numpy as np

from monotracker import __version__
from monotracker.engine.persistence import atomic_write_json
from monotracker.engine.snapshot import CommandResult, RecordingSummary
from monotracker.errors import InputError, MonoTrackerError
from monotracker.vision.replay_source import FORMAT, FRAMES_DIR, MANIFEST, VERSION

log = logging.getLogger(__name__)

STREAMS = ("frames", "detections", "poses", "robot", "targets", "alerts", "events")
#: PNG compression 1: fast (the rendered 1280x720 frames carry sensor noise, so higher levels gain little)
PNG_LEVEL = 1
QUEUE_FRAMES = 64
#: made at the start and deleted when the disk fills, so the final manifest can still be written
RESERVE_FILE = ".reserve"
RESERVE_BYTES = 1 << 20
#: free space a recording needs to start (the rendered twin writes ~45 MB/s at 30 fps)
MIN_FREE_BYTES = 256 << 20


def _num(v):
    """JSON-safe number: NaN/inf -> None (float repr round-trips exactly in JSON)."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _clean(o):
    """JSON-ready copy: arrays to lists, numpy scalars to Python, NaN/inf to None."""
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, (int, np.integer)):
        return int(o)
    if isinstance(o, (float, np.floating)):
        return _num(o)
    if o is None or isinstance(o, str):
        return o
    return str(o)


def _mat(a):
    return None if a is None else [[_num(x) for x in row] for row in np.asarray(a, float).reshape(-1, np.asarray(a).shape[-1])]


def _write_reserve(path: Path) -> None:
    """:data:`RESERVE_BYTES` of zeros, on disk (fsync'ed): freed when the disk fills."""
    with open(path, "wb") as fh:
        fh.write(b"\0" * RESERVE_BYTES)
        fh.flush()
        os.fsync(fh.fileno())


def _write_json(path: Path, data: dict) -> None:
    atomic_write_json(path, data)


class RecordingWriter:
    """The files of one recording (see the module docstring). ``block``: wait when the queue is
    full (simulated clock) instead of dropping the frame (real clock). ``min_free_bytes``: the
    free space the folder needs to start (:class:`InputError` otherwise)."""

    def __init__(self, folder: str | Path, manifest: dict, block: bool, min_free_bytes: int = MIN_FREE_BYTES):
        self.folder = Path(folder)
        if (self.folder / MANIFEST).exists():
            raise InputError(f"{self.folder} already holds a recording; choose an empty folder")
        if self.folder.exists() and not self.folder.is_dir():
            raise InputError(f"--record {self.folder}: not a folder")
        self.manifest = dict(manifest)
        self.manifest.update(format=FORMAT, version=VERSION, complete=False, frames=0, frames_dropped=0)
        self._files = {}
        try:
            (self.folder / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
            free = shutil.disk_usage(self.folder).free
            if free < min_free_bytes:
                raise InputError(f"cannot record to {self.folder}: only {free >> 20} MiB free (a recording needs "
                                 f"at least {min_free_bytes >> 20} MiB to start; about 45 MB per second of "
                                 "rendered frames)")
            _write_reserve(self.folder / RESERVE_FILE)
            self._files = {k: open(self.folder / f"{k}.jsonl", "a", encoding="utf-8") for k in STREAMS}
            _write_json(self.folder / MANIFEST, self.manifest)
        except OSError as exc:
            self._close_files()
            raise InputError(f"cannot record to {self.folder}: {exc.strerror or exc}") from None
        self.block = bool(block)
        self.frames = 0           # frames accepted (queued)
        self.dropped = 0
        self.error: str | None = None
        self.truncated = False
        self._counts = {k: 0 for k in STREAMS}
        self._good = {k: (self._files[k].buffer.tell(), 0) for k in STREAMS}  # (offset, rows) after the last whole item
        self._q: queue.Queue = queue.Queue(maxsize=QUEUE_FRAMES)
        self._lock = threading.Lock()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="monotracker-recorder", daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        return not self._closed and self.error is None

    def write_json_file(self, name: str, data: dict) -> None:
        self._put(("json", name, data), frame=False)

    def line(self, stream: str, row: dict) -> None:
        self._put(("line", stream, row), frame=False)

    def frame(self, row: dict, image: np.ndarray | None, rows: dict) -> bool:
        """Queue one frame (its ``frames`` row, the image or None, and rows of other streams).
        False if it was dropped."""
        with self._lock:
            if not self.running:
                return False
            seq = self.frames
            self.frames += 1
        row = dict(row, seq=seq)
        if image is not None:
            row["file"] = f"{FRAMES_DIR}/{seq:06d}.png"
        ok = self._put(("frame", row, image, rows), frame=True)
        if not ok:
            with self._lock:
                self.dropped += 1  # its seq stays unused; the manifest counts the drop
        return ok

    def _put(self, item, frame: bool) -> bool:
        if self.block or not frame:
            self._q.put(item)
            return True
        try:
            self._q.put_nowait(item)
            return True
        except queue.Full:
            return False

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            if self.error is not None:
                continue  # failed: drain without writing
            try:
                self._handle(item)
                self._commit()
            except Exception as exc:  # a full disk must not kill the engine
                if isinstance(exc, OSError):
                    log.warning("recording to %s stopped: %s", self.folder, exc)
                    self.error = f"{exc.strerror or exc}" + (f" (errno {exc.errno})" if exc.errno else "")
                else:
                    log.exception("recording failed")
                    self.error = f"{type(exc).__name__}: {exc}"
                self._cut_back(item)
                self._write_final_manifest()  # now, not at close: a crash later must not lose the rest

    def _handle(self, item) -> None:
        kind = item[0]
        if kind == "json":
            _write_json(self.folder / item[1], item[2])
        elif kind == "line":
            self._write_line(item[1], item[2])
        else:
            _, row, image, rows = item
            if image is not None:
                ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL])
                if not ok:
                    raise OSError(f"PNG encoding failed for frame {row['seq']}")
                data = buf.tobytes()
                (self.folder / row["file"]).write_bytes(data)
                row["sha256"] = hashlib.sha256(data).hexdigest()
            self._write_line("frames", row)
            for stream, r in rows.items():
                self._write_line(stream, dict(r, seq=row["seq"]))

    def _write_line(self, stream: str, row: dict) -> None:
        self._files[stream].write(json.dumps(_clean(row), allow_nan=False) + "\n")
        self._counts[stream] += 1

    def _commit(self) -> None:
        """Flush every stream: the item just handled is on disk whole; remember where it ends."""
        for fh in self._files.values():
            fh.flush()
        self._good = {k: (fh.buffer.tell(), self._counts[k]) for k, fh in self._files.items()}

    def _cut_back(self, item) -> None:
        """A write failed: cut every stream back to the end of the last whole item (truncating
        needs no free space), remove the failed frame's image, free the reserve."""
        self.truncated = True
        for k, fh in self._files.items():
            off, rows = self._good[k]
            try:
                fh.close()  # may fail to flush its buffer: the cut below discards it anyway
            except OSError:
                pass
            try:
                os.truncate(self.folder / f"{k}.jsonl", off)
            except OSError as exc:
                log.warning("recording stream %s not cut back: %s", k, exc)
            self._counts[k] = rows
        self._files = {}
        if item[0] == "frame" and item[1].get("file"):
            try:
                (self.folder / item[1]["file"]).unlink()
            except OSError:
                pass
        try:
            (self.folder / RESERVE_FILE).unlink()
        except OSError:
            pass

    def _close_files(self) -> None:
        for fh in self._files.values():
            try:
                fh.close()
            except OSError as exc:
                self.error = getattr(self, "error", None) or str(exc)
        self._files = {}

    def close(self, extra: dict | None = None) -> dict:
        """Flush, close, and mark the manifest complete (unless a write failed). Idempotent."""
        with self._lock:
            if self._closed:
                return self.manifest
            self._closed = True
        self._q.put(None)
        self._thread.join()
        if self._files:
            try:
                self._commit()
            except OSError as exc:
                self.error = self.error or f"{exc.strerror or exc}"
                self._cut_back(("close",))
        self._close_files()
        try:
            (self.folder / RESERVE_FILE).unlink()
        except OSError:
            pass
        self.manifest.update(extra or {})
        self._write_final_manifest()
        return self.manifest

    def _write_final_manifest(self) -> None:
        """The manifest with the counts of what is on disk (``truncated`` after a failed write)."""
        self.manifest.update(frames=self._counts["frames"], frames_dropped=self.dropped,
                             counts=dict(self._counts), error=self.error,
                             closed_utc=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds"))
        self.manifest["complete"] = self.error is None
        if self.truncated:
            self.manifest["truncated"] = True  # what is there is whole: replayable up to here
        try:
            _write_json(self.folder / MANIFEST, self.manifest)
        except OSError as exc:
            self.error = self.error or str(exc)
            self.manifest["manifest_error"] = str(exc)


def _versions() -> dict:
    import platform

    import scipy

    return {"monotracker": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "opencv": cv2.__version__, "scipy": scipy.__version__}


class SessionRecorder:
    """Records a session into ``folder`` from now until :meth:`close` (see the module docstring)."""

    def __init__(self, session, loop, folder: str | Path):
        """``session``: what is recorded about the session (config, plan, events); ``loop``: the
        tracking loop whose estimates, camera segments, robot and targets are recorded."""
        self.s = session
        self._loop = loop
        plan = session.plan_copy()
        cfg = session.config
        manifest = {
            "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds"),
            "versions": _versions(),
            "session_id": session.session_id,
            "camera": cfg.camera, "clock": cfg.clock, "robot": cfg.robot,
            "trajectory": cfg.trajectory if isinstance(cfg.trajectory, str) else repr(cfg.trajectory),
            "seed": cfg.seed, "camera_fps": cfg.camera_fps,
            "units": {"length": "mm", "time": "s (session clock)", "image": "px", "joints": "rad"},
            "frame": "CT points LPS; camera OpenCV (x right, y down, z forward); T_to_from 4x4",
            "segments": [],
        }
        self.writer = RecordingWriter(folder, manifest, block=cfg.clock == "sim")
        self.folder = self.writer.folder
        self.writer.write_json_file("plan.json", plan.to_dict())
        self._rig = None
        rig0 = loop.camera.rig
        self._rig_at_start = rig0 if rig0 is not None and rig0.running else None
        self._segment = 0
        self._calibration: tuple | None = None
        self._last_target_stamp = None
        self._fids: list[int] = []
        self._closed = False
        self._failure_reported = False
        self._remove_hook = loop.add_pose_hook(self._on_pose)
        self._unsubscribe = session.subscribe(self._on_event)

    # ------------------------------------------------------------------ status
    def summary(self) -> dict:
        w = self.writer
        return {"path": str(self.folder), "frames": w.frames - w.dropped, "running": w.running and not self._closed,
                "dropped": w.dropped, "error": w.error}

    def snapshot_summary(self):
        d = self.summary()
        return RecordingSummary(d["path"], int(d["frames"]), bool(d["running"]), int(d["dropped"]), d["error"])

    # ------------------------------------------------------------------ hooks
    def _on_event(self, ev) -> None:
        if self._closed:
            return
        self.writer.line("alerts" if ev.kind == "alert" else "events", ev.as_dict())

    def _new_segment(self, rig) -> None:
        self._rig = rig
        self._segment += 1
        cal = None if rig.K is None else (np.asarray(rig.K, float), np.asarray(rig.dist, float).ravel(),
                                          tuple(int(v) for v in rig.image_size))
        name = None
        if cal is not None:
            same = self._calibration is not None and all(
                np.array_equal(a, b) for a, b in zip(self._calibration[:2], cal[:2])) and self._calibration[2] == cal[2]
            name = "calibration.json" if self._calibration is None or same else f"calibration-{self._segment}.json"
            if not same:
                if self._calibration is None:
                    self._calibration = cal
                self.writer.write_json_file(name, {"camera_matrix": cal[0].tolist(),
                                                   "distortion_coefficients": cal[1].tolist(),
                                                   "image_width": cal[2][0], "image_height": cal[2][1]})
        plan = self.s.plan_copy()
        self._fids = [f.id for f in plan.registration_fiducials()]  # what the rig registers (in this order)
        self.writer.manifest["segments"].append({
            "segment": self._segment, "source": self._loop.camera.source, "calibration": name,
            "fiducial_ids": self._fids, "fiducials_lps_mm": plan.registration_centres().tolist(),
            "radius_mm": float(np.median([f.radius_mm for f in plan.registration_fiducials()])),
            "target_lps_mm": None if plan.target_lps_mm is None else plan.target_lps_mm.tolist(),
            # the camera was already running when recording began: its tracker had a history
            "mid_stream": rig is self._rig_at_start,
        })

    def _on_pose(self, smp, trusted: bool, now: float) -> None:
        if self._closed:
            return
        if self.writer.error is not None:
            if not self._failure_reported:
                self._failure_reported = True
                kept = self.writer._counts["frames"]
                self.s.alert("alarm", "recording_failed",
                             f"recording to {self.folder} stopped: {self.writer.error}; the {kept} frames before are "
                             "kept and replay (the manifest marks it truncated)",
                             {"folder": str(self.folder), "frames_kept": kept, "error": self.writer.error})
            return
        loop = self._loop
        rig = loop.camera.rig
        if rig is not None and rig is not self._rig:
            self._new_segment(rig)
        raw = smp.raw
        payload = smp.frame
        row = {"index": int(smp.frame_index), "t_capture": float(smp.t_capture), "segment": self._segment,
               "camera": getattr(raw, "camera", "ok")}
        image = None
        if row["camera"] != "ok":
            row["kind"] = "fault"  # frozen/stalled/ended: the tracker was reset, no image processed
        elif isinstance(payload, np.ndarray):
            row["kind"], image = "image", payload
        elif payload is not None and hasattr(payload, "points_px"):
            row["kind"] = "points"
            row["points_px"] = _mat(payload.points_px) if len(payload.points_px) else []
            minor = getattr(payload, "minor_px", None)
            if minor is not None:
                row["minor_px"] = [_num(v) for v in np.asarray(minor, float).ravel()]
        else:
            row["kind"] = "none"
        rows = {"poses": {
            "index": int(smp.frame_index), "t_capture": float(smp.t_capture), "t_ready": _num(smp.t_ready),
            "ok": bool(smp.ok), "trusted": bool(trusted), "reason": smp.reason,
            "T_cam_ct": _mat(smp.T_cam_ct), "n_matched": int(smp.n_matched), "fre_mm": _num(smp.fre_mm),
            "predicted_tre_mm": _num(smp.predicted_tre_mm), "fault": getattr(rig, "fault", "none"),
            "truth_T_cam_ct": _mat(smp.truth_T_cam_ct), "truth_tre_mm": _num(smp.truth_tre_mm)}}
        pts = getattr(raw, "image_points_px", None)
        rows["detections"] = {
            "index": int(smp.frame_index), "t_capture": float(smp.t_capture),
            "n_detected": int(getattr(raw, "n_detected", len(getattr(payload, "points_px", ())))),
            "status": {str(k): v for k, v in smp.fiducial_status.items()},
            "residuals_px": {str(k): _num(v) for k, v in smp.residuals_px.items()},
            "image_points_px": None if pts is None else {
                str(self._fids[j]): [_num(p[0]), _num(p[1])] for j, p in enumerate(np.asarray(pts, float))
                if j < len(self._fids) and np.all(np.isfinite(p))}}
        rob = loop.robot.rig
        if rob is not None:
            st = rob.status()
            rows["robot"] = {"t": float(now), "state": st.state, "connected": bool(st.connected),
                             "q_rad": None if st.q is None else [_num(v) for v in st.q],
                             "T_base_tip": _mat(st.T_base_tip), "speed_mm_s": _num(st.speed_mm_s),
                             "message": st.message}
        T, stamp = loop.target()
        if T is not None and stamp != self._last_target_stamp:
            self._last_target_stamp = stamp
            rows["targets"] = {"t": float(now), "stamp": _num(stamp), "T_base_target": _mat(T)}
        if not self.writer.frame(row, image, rows) and self.writer.dropped == 1:
            self.s.alert("warning", "recording_dropping",
                         f"recording to {self.folder} cannot keep up: frames are being dropped "
                         "(the recording will not replay)")

    # ------------------------------------------------------------------ close
    def close(self) -> dict:
        """Detach and close; returns the final manifest."""
        if self._closed:
            return self.writer.manifest
        self._closed = True
        self._remove_hook()
        self._unsubscribe()
        return self.writer.close()


# ---------------------------------------------------------------------- the session's part
class Recording:
    """The session's recording part: one :class:`SessionRecorder` at a time (``Session.start_recording``
    / ``stop_recording``); ``lock``: the session's state lock."""

    def __init__(self, session, loop, lock):
        self._session = session
        self._loop = loop
        self._lock = lock
        self.recorder: SessionRecorder | None = None  # while and after recording

    def start(self, folder) -> CommandResult:
        """Record into ``folder`` (an empty or new folder) until :meth:`stop`."""
        session = self._session
        with self._lock:
            rec = self.recorder
            if rec is not None and not rec._closed:
                if rec.writer.running:
                    return CommandResult(False, f"already recording to {rec.folder}")
                rec.close()  # a failed recording: detach it before starting another
            try:
                self.recorder = SessionRecorder(session, self._loop, folder)
            except MonoTrackerError as exc:
                return CommandResult(False, str(exc))
        session.record("recording_started", f"recording to {folder}", {"folder": str(folder)})
        return CommandResult(True, f"recording to {folder}")

    def stop(self) -> CommandResult:
        """Close the recording and report (an alert if it is incomplete). Idempotent."""
        session = self._session
        rec = self.recorder
        if rec is None or rec._closed:
            return CommandResult(True, "not recording")
        m = rec.close()
        if not m.get("complete"):
            why = m.get("error") or f"{m.get('frames_dropped')} frames dropped"
            kept = f"; the {m.get('frames')} frames before the failure are kept" if m.get("truncated") else ""
            if not rec._failure_reported:
                session.alert("warning", "recording_failed", f"recording {rec.folder} is incomplete: {why}{kept}")
            return CommandResult(False, f"recording {rec.folder} is incomplete ({why}){kept}")
        session.record("recording_stopped", f"recording closed: {m['frames']} frames in {rec.folder}",
                       {"folder": str(rec.folder), "frames": m["frames"]})
        return CommandResult(True, f"recording closed: {m['frames']} frames")

    def summary(self):
        """``snap.recording``: None when nothing was recorded in this session."""
        rec = self.recorder
        return None if rec is None else rec.snapshot_summary()
