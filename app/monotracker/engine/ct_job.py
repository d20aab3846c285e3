"""The session's CT job: load a CT (DICOM folder, NIfTI, NRRD, MHA) on a job thread, detect the
fiducials, build the head surface; or detect again with a new fiducial kit.

Progress and errors go to ``snap.job``; a failure is an alarm with one line, never a traceback.
:class:`CTJob` is a part of the :class:`~monotracker.engine.session.Session`: it holds the loaded
CT (:class:`LoadedCT`) and the job, and changes the plan only through the plan editor's
transactions (``engine/plan/editor.py``)."""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from monotracker.engine.plan import checks as plan_checks
from monotracker.engine.plan.editor import Refused
from monotracker.engine.plan.model import PlanFiducial
from monotracker.engine.snapshot import (
    CommandResult,
    CTRejectedBlob,
    CTSummary,
    HeadMesh,
    Job,
    frozen_array,
)
from monotracker.errors import MonoTrackerError

log = logging.getLogger(__name__)


class JobCancelled(Exception):
    """The CT job was cancelled (operator) or ran past ``ct_job_timeout_s``; ``str`` is the line."""


class JobToken:
    """One CT job's cancel flag: set by :meth:`CTJob.cancel_ct_job` or the timeout; the
    job checks it between its stages (and the fiducial search inside its loop) and then
    discards its results, so the previous CT and plan stay."""

    def __init__(self):
        self._event = threading.Event()
        self.reason = ""
        self.committed = False  # the job is storing its results: too late to stop it
        self.timer: threading.Timer | None = None

    def cancel(self, reason: str) -> bool:
        """Flag the job; False when it was already flagged (the first reason stays)."""
        if self._event.is_set():
            return False
        self.reason = reason
        self._event.set()
        return True

    @property
    def cancelled(self) -> bool:
        return self._event.is_set()

    def check(self) -> None:
        if self._event.is_set():
            raise JobCancelled(self.reason)


def detected_fiducials(det) -> list:
    """The plan's fiducials from a detection: ids 0.., status ``detected``."""
    return [PlanFiducial(i, np.asarray(f.centre_lps, float), float(f.radius_mm), float(f.score), "detected")
            for i, f in enumerate(det.fiducials)]


def rejected_summary(det, vol) -> tuple:
    """``det.rejected`` as :class:`CTRejectedBlob` rows (radius: fitted, else of a ball of the
    blob's volume, mm)."""
    voxel_mm3 = float(np.prod(vol.spacing_mm))
    out = []
    for r in det.rejected:
        rad = float(r.radius_mm) if np.isfinite(r.radius_mm) else float((3.0 * r.n_voxels * voxel_mm3 / (4.0 * np.pi)) ** (1 / 3))
        out.append(CTRejectedBlob(tuple(round(float(x), 2) for x in r.centre_lps), round(rad, 2), int(r.n_voxels), str(r.reason)))
    return tuple(out)


@dataclass(frozen=True)
class LoadedCT:
    """The CT the session has loaded: ``summary`` (for ``snap.ct``), ``volume`` (LPS mm),
    ``head_mesh`` (:class:`HeadMesh`, or None) with its outward vertex ``head_normals`` (n, 3),
    ``anatomy`` (what the plan's checks read of it) and ``sha256`` (content hash, or None)."""

    summary: CTSummary
    volume: object
    head_mesh: HeadMesh | None
    head_normals: np.ndarray | None
    anatomy: plan_checks.Anatomy
    sha256: str | None


class CTJob:
    """The session's CT job (see the module docstring). Collaborators: the state ``lock``, the
    plan ``editor``, the event bus and alarm board, the session ``clock`` (s), the ``config``
    (``ct_job_timeout_s``) and ``plan_changed(why, restart_camera)`` of the tracking loop."""

    def __init__(self, *, lock, editor, events, alarms, clock, config, plan_changed):
        self._lock = lock
        self._editor = editor
        self._bus = events
        self._alarm_board = alarms
        self.clock = clock
        self.config = config
        self._plan_changed = plan_changed
        self._job: Job | None = None
        self._job_thread: threading.Thread | None = None
        self._ct_token: JobToken | None = None
        self.loaded: LoadedCT | None = None

    @property
    def job(self) -> Job | None:
        """The current or last job (``snap.job``)."""
        return self._job

    def forget(self) -> None:
        """Drop the loaded CT (a new plan); the caller holds the state lock."""
        self.loaded = None

    def load_sample_ct(self) -> CommandResult:
        """:meth:`load_ct` on the bundled phantom CT (``paths.sample_ct_path()``); same refusals."""
        from monotracker.paths import sample_ct_path

        return self.load_ct(sample_ct_path())

    def load_ct(self, path, series: str | None = None) -> CommandResult:
        """Start the CT job (load, detect fiducials, head surface). Progress in ``snap.job``.
        ``series``: the DICOM Series Instance UID to load from a folder holding several
        (``monotracker.ct.list_series(path)`` lists them); None picks the largest (noted).

        If the plan's fiducials are locked, the CT must be the one the plan was made on: its volume
        and surface are reloaded and the saved fiducials are kept (restart after a crash).

        Args:
            path: DICOM folder or volume file (see :func:`monotracker.ct.load_volume`).
            series: Series Instance UID, or None.

        Returns:
            :class:`CommandResult` at once; the job's outcome (``snap.job.error``, alerts
            ``ct_failed`` / ``fiducials_detection``) comes later, :meth:`wait_for_job` waits for it.

        Refuses (ok=False, message): another job still running; the plan's fiducials are
        locked on another CT; no such path.
        """
        path = str(path)
        with self._lock:
            if self._job is not None and not self._job.done:
                return CommandResult.refused(f"busy: {self._job.name} is still running")
            plan = self._editor.plan
            if plan.fiducials_locked and plan.ct_path and Path(plan.ct_path) != Path(path):
                return CommandResult.refused("the plan's fiducials are locked on another CT; start a new plan first")
            if not Path(path).exists():
                return CommandResult.refused(f"no such file or folder: {path}")
            self._job = Job("load_ct", 0.0, f"loading {Path(path).name}")
            token = self._new_job_token()
            th = threading.Thread(target=self._ct_job, args=(path, series, token), name="monotracker-ct", daemon=True)
            self._job_thread = th
        self._alarm_board.clear("ct_failed", float(self.clock()))
        self._bus.event("ct_load_started", f"loading CT {path}", {"path": path})
        self._start_job(th, token)
        return CommandResult.done("loading CT")

    # ------------------------------------------------------------------ cancel and timeout
    def _new_job_token(self) -> JobToken:
        """A fresh token for the job about to start (caller holds the lock)."""
        self._ct_token = JobToken()
        return self._ct_token

    def _start_job(self, th: threading.Thread, token: JobToken) -> None:
        """Start the job thread and its overall timeout (``config.ct_job_timeout_s``)."""
        limit = float(self.config.ct_job_timeout_s)
        timer = threading.Timer(limit, self._stop_ct_job, args=(token, f"the CT job ran past its {limit:g} s limit "
                                                                       "(ct_job_timeout_s) and was stopped"))
        timer.daemon = True
        token.timer = timer
        timer.start()
        th.start()

    def cancel_ct_job(self) -> CommandResult:
        """Cancel the running CT job (load, detection, surface). The job stops at its next
        stage (the fiducial search at once); whatever it had made is discarded: the previous
        CT, fiducials and plan stay as they were. ``snap.job`` says so at once.

        Refuses (ok=False): no CT job is running."""
        with self._lock:
            token = self._ct_token
            running = self._job is not None and not self._job.done
        if token is None or not running:
            return CommandResult.refused("no CT job is running")
        if not self._stop_ct_job(token, "cancelled by the operator"):
            return CommandResult.refused("no CT job is running")
        return CommandResult.done("CT job cancelled; the previous CT and plan are unchanged")

    def _stop_ct_job(self, token: JobToken, reason: str) -> bool:
        """Flag ``token``'s job and end it in ``snap.job`` now (the thread winds down by
        itself). False when that job had already ended or been stopped."""
        with self._lock:
            if (token is not self._ct_token or token.committed or self._job is None
                    or self._job.done):
                return False
            if not token.cancel(reason):
                return False
            name = self._job.name
            self._job = Job(name, 1.0, "CT job stopped", f"{reason}; the previous CT and plan are unchanged", True)
        self._bus.alert("warning", "ct_job_stopped", f"CT job stopped: {reason}", {"job": name})
        return True

    def _job_ended(self, token: JobToken) -> None:
        if token.timer is not None:
            token.timer.cancel()

    def set_fiducial_kit(self, radius_mm, density_hu=None) -> CommandResult:
        """Set the fiducial kit (nominal ball radius, mm; material density, HU, None = unknown),
        kept in the plan, and re-run the fiducial detection on the loaded CT as the CT job
        (progress in ``snap.job``; :meth:`wait_for_job` waits for it). The new detection
        replaces the detected fiducials and the decisions on them; fiducials the operator added
        are kept unless the new detection finds the same ball. Without a CT the kit is only kept.

        Refuses (ok=False, one line): radius missing, not a finite number or outside 0.5-20 mm;
        density not a finite number or outside 300-30000 HU; the fiducials are locked; a job is
        running; the plan cannot be saved."""
        why = plan_checks.check_fiducial_kit(radius_mm, density_hu)
        if why:
            return CommandResult.refused(why)
        from monotracker.ct.kit import FiducialKit

        kit = FiducialKit(float(radius_mm), None if density_hu is None else float(density_hu))
        with self._lock:
            if self._job is not None and not self._job.done:
                return CommandResult.refused(f"busy: {self._job.name} is still running")
            if self._editor.plan.fiducials_locked:
                return CommandResult.refused("fiducials are locked; unlock them first (a new kit re-runs the detection)")
            old = self._editor.plan.fiducial_kit
            vol = None if self.loaded is None else self.loaded.volume
            if vol is None:  # no CT: the kit alone goes into the plan now
                try:
                    with self._editor.edit("fiducial kit") as plan:
                        plan.fiducial_kit = kit
                except Refused as exc:
                    return CommandResult.refused(str(exc))
                th = None
            else:  # with a CT, the kit is committed with the fiducials it finds (a stopped job changes nothing)
                self._job = Job("detect_fiducials", 0.0, "detecting fiducials with the new kit")
                token = self._new_job_token()
                th = threading.Thread(target=self._detect_job, args=(vol, kit, token), name="monotracker-ct", daemon=True)
                self._job_thread = th
        if th is None:
            self._kit_set_event(kit, old)
            return CommandResult.done("fiducial kit kept in the plan; it is used when a CT is loaded")
        self._start_job(th, token)
        return CommandResult.done("detecting the fiducials with the new kit; the plan takes the kit when the detection ends")

    def _kit_set_event(self, kit, old) -> None:
        self._bus.event("fiducial_kit_set", f"fiducial kit: radius {kit.radius_mm:g} mm, density "
                        + ("unknown" if kit.density_hu is None else f"{kit.density_hu:g} HU"),
                        {"kit": kit.to_dict(), "previous": None if old is None else old.to_dict()})

    def _detect_job(self, vol, kit, token: JobToken) -> None:
        """The CT job of :meth:`set_fiducial_kit`: detection on the loaded volume, then the plan."""
        try:
            self._detect_job_body(vol, kit, token)
        finally:
            self._job_ended(token)

    def _detect_job_body(self, vol, kit, token: JobToken) -> None:
        try:
            from monotracker.ct import detect_fiducials

            det = detect_fiducials(vol, kit=kit, cancel=lambda: token.cancelled)
            token.check()
        except JobCancelled:
            return
        except Exception as exc:  # report, never kill the engine
            log.exception("fiducial detection failed")
            self._set_job(1.0, "detection failed", f"internal error: {type(exc).__name__}: {exc}", True, token)
            self._bus.alert("alarm", "ct_failed", f"fiducial detection failed: {type(exc).__name__}: {exc}")
            return
        with self._lock:
            if token.cancelled:
                return
            token.committed = True
            loaded = self.loaded
            if loaded is None or loaded.volume is not vol or self._editor.plan.fiducials_locked:
                self._job = Job("detect_fiducials", 1.0, "detection not used; fiducial kit not changed",
                                "the CT or the plan changed meanwhile", True)
                return
            try:
                with self._editor.edit("fiducials detected again (new kit)") as plan:
                    old_kit = plan.fiducial_kit
                    plan.fiducial_kit = kit
                    new = detected_fiducials(det)
                    kept = [f for f in plan.fiducials if f.status == "added"
                            and all(np.linalg.norm(np.asarray(f.centre_lps_mm) - g.centre_lps_mm)
                                    >= f.radius_mm + g.radius_mm for g in new)]
                    dropped = sum(f.status == "added" for f in plan.fiducials) - len(kept)
                    for k, f in enumerate(kept):
                        f.id = len(new) + k
                    plan.fiducials = new + kept
            except Refused as exc:
                self._job = Job("detect_fiducials", 1.0, "detection not used; fiducial kit not changed",
                                f"the plan could not be saved: {exc}", True)
                return
            summary = replace(loaded.summary, rejected=rejected_summary(det, vol), detection=det.reason)
            self.loaded = replace(loaded, summary=summary)
        self._kit_set_event(kit, old_kit)
        self._plan_changed("fiducials detected again (new kit)", False)
        extra = f"; {dropped} added fiducial(s) now detected" if dropped else ""
        self._set_job(1.0, ("fiducials detected again" if det.ok else f"fiducials: {det.reason}") + extra, None, True, token)
        self._bus.event("fiducials_detected", f"{len(det.fiducials)} fiducials detected in the CT (new kit)"
                        + ("" if det.ok else f" ({det.reason})"),
                        {"ok": bool(det.ok), "reason": det.reason, "kit": kit.to_dict(),
                         "centres_lps_mm": [np.asarray(f.centre_lps).tolist() for f in det.fiducials]})
        if not det.ok:
            self._bus.alert("warning", "fiducials_detection", f"fiducial detection: {det.reason}")

    def wait_for_job(self, timeout: float | None = None) -> Job | None:
        """Block until the current job ends (for scripts and tests; the UI polls snapshots).

        ``timeout``: seconds, None = no limit. Returns the last :class:`Job` (``done``,
        ``error`` one line or None) or None when no job ever ran; ``done`` is False if the
        timeout expired first."""
        th = self._job_thread
        if th is not None:
            th.join(timeout)
        with self._lock:
            return self._job

    def _hash_ct(self, path: str) -> str | None:
        """SHA-256 of the CT file or DICOM folder (on the CT job's thread); None if unreadable."""
        from monotracker.engine.integrity import content_sha256

        try:
            return content_sha256(path)
        except OSError as exc:
            self._bus.alert("warning", "ct_hash_failed", f"the CT's content hash could not be computed: {exc}")
            return None

    def _ct_failed_alarm(self) -> None:
        self._alarm_board.set("ct_failed", "the last CT could not be loaded (see the CT step)", float(self.clock()))

    def _set_job(self, progress: float, message: str, error: str | None = None, done: bool = False,
                 token: JobToken | None = None) -> None:
        """Update ``snap.job``; ignored for a job that was stopped (``token`` cancelled)."""
        with self._lock:
            if token is not None and (token.cancelled or token is not self._ct_token):
                return
            name = self._job.name if self._job else "job"
            self._job = Job(name, progress, message, error, done)

    def _ct_job(self, path: str, series: str | None = None, token: JobToken | None = None) -> None:
        token = token or JobToken()
        try:
            self._ct_job_body(path, series, token)
        finally:
            self._job_ended(token)

    def _ct_job_body(self, path: str, series: str | None, token: JobToken) -> None:
        got = self._load_stages(path, series, token)
        if got is None:
            return  # stopped (snap.job says why) or failed (reported)
        vol, det, mesh, anatomy, ct_sha = got
        kept = self._keep(path, vol, det, mesh, anatomy, ct_sha, token)
        if kept is None:
            return
        restored, recorded = kept
        if restored and recorded and ct_sha and recorded != ct_sha:
            self._editor.need_reconfirm("plan_ct_changed", f"the CT {path} changed since the plan was made "
                                        "(content hash differs)", {"path": path, "recorded": recorded, "now": ct_sha})
        if restored:
            plan = self._editor.plan
            why = plan_checks.check_path(plan.entry_lps_mm, plan.target_lps_mm, plan.fiducials,
                                         anatomy) if plan.path_complete else None
            if why:
                self._bus.alert("alarm", "plan_path_invalid", f"the restored path fails its check on the CT: {why}")
        if not restored:
            self._plan_changed("new CT loaded", False)
        self._set_job(1.0, "CT ready" if det.ok else f"CT ready; fiducials: {det.reason}", None, True, token)
        if restored:
            self._bus.event("ct_reloaded", f"CT reloaded for the saved plan: {path}", {"path": path})
        else:
            self._bus.event("fiducials_detected", f"{len(det.fiducials)} fiducials detected in the CT"
                            + ("" if det.ok else f" ({det.reason})"),
                            {"path": path, "ok": bool(det.ok), "reason": det.reason,
                             "centres_lps_mm": [np.asarray(f.centre_lps).tolist() for f in det.fiducials]})
            if not det.ok:
                self._bus.alert("warning", "fiducials_detection", f"fiducial detection: {det.reason}")

    def _load_stages(self, path: str, series: str | None, token: JobToken):
        """Load, detect, surface, anatomy, content hash: ``(vol, det, mesh, anatomy, sha256)``, or
        None when the job was stopped or failed (then ``snap.job`` and a ``ct_failed`` alarm say why)."""
        try:
            from monotracker.ct import detect_fiducials, load_volume
        except ImportError as exc:
            self._set_job(1.0, "CT tools unavailable", f"CT tools are not installed: {exc}", True, token)
            self._ct_failed_alarm()
            self._bus.alert("alarm", "ct_failed", f"CT tools are not available: {exc}")
            return None
        try:
            vol = load_volume(path, series=series)
            token.check()
            self._set_job(0.3, "detecting fiducials", token=token)
            with self._lock:
                kit = self._editor.plan.fiducial_kit
            det = detect_fiducials(vol, kit=kit, cancel=lambda: token.cancelled)
            token.check()
            self._set_job(0.6, "extracting the head surface", token=token)
            try:
                from monotracker.ct import head_surface
            except ImportError:  # older ct package: no surface, the plan still works
                head_surface = None
            mesh = head_surface(vol) if head_surface is not None else None
            token.check()
            self._set_job(0.8, "checking the CT's content hash", token=token)
            anatomy = plan_checks.Anatomy.from_ct(vol, mesh)
            ct_sha = self._hash_ct(path)
            token.check()
        except JobCancelled:
            return None  # snap.job already says why; nothing of this job is kept
        except MonoTrackerError as exc:
            if token.cancelled:
                return None
            self._set_job(1.0, "CT failed", str(exc), True, token)
            self._ct_failed_alarm()
            self._bus.alert("alarm", "ct_failed", f"CT could not be used: {exc}", {"path": path})
            return None
        except Exception as exc:  # report, never kill the engine
            if token.cancelled:
                return None
            log.exception("CT job failed")
            self._set_job(1.0, "CT failed", f"internal error: {type(exc).__name__}: {exc}", True, token)
            self._ct_failed_alarm()
            self._bus.alert("alarm", "ct_failed", f"CT job failed: {type(exc).__name__}: {exc}", {"path": path})
            return None
        return vol, det, mesh, anatomy, ct_sha

    def _keep(self, path: str, vol, det, mesh, anatomy, ct_sha, token: JobToken):
        """Keep the job's result: a new plan on this CT (saved first, then swapped in with the
        volume) or, for the plan's own CT after a restart, the volume alone. Returns
        ``(restored, the plan's recorded CT hash)``, or None when stopped or not saved."""
        with self._lock:
            if token.cancelled:  # stopped while finishing: the previous CT and plan stay
                return None
            token.committed = True  # from here on the job cannot be stopped: it is being kept
            current = self._editor.plan
            restored = current.fiducials_locked and current.ct_path == path
            recorded = current.integrity.get("ct_sha256")
            if not restored:
                try:
                    with self._editor.edit("CT loaded") as plan:
                        plan.ct_path = path
                        plan.fiducials = detected_fiducials(det)
                        plan.fiducials_locked = False
                        plan.entry_lps_mm = None
                        plan.target_lps_mm = None
                        plan.integrity["ct_sha256"] = ct_sha
                except Refused as exc:
                    self._job = Job(self._job.name if self._job else "load_ct", 1.0, "CT not used",
                                    f"the new plan could not be saved: {exc}", True)
                    return None
            summary = CTSummary(path=path, shape=tuple(int(v) for v in vol.array.shape),
                                spacing_mm=tuple(float(v) for v in vol.spacing_mm),
                                notes=tuple(getattr(vol, "notes", ()) or ()),
                                rejected=rejected_summary(det, vol), detection=det.reason)
            head_mesh = head_normals = None
            if mesh is not None:
                head_mesh = HeadMesh(frozen_array(np.asarray(mesh.vertices, float)),
                                     frozen_array(np.asarray(mesh.faces), np.int64))
                head_normals = np.asarray(mesh.vertex_normals, dtype=float)
            self.loaded = LoadedCT(summary, vol, head_mesh, head_normals, anatomy, ct_sha)
        return restored, recorded
