"""Where the plan lives on disk: the saved ``plan.json``, restored field by field with the same
checks the commands use, and the one way a changed plan is committed (saved, then swapped in).

:func:`restore_plan` never raises for a file that is a MonoTracker plan: each field that fails its
check (:mod:`~monotracker.engine.plan.checks`) is left out and named in the returned rejections,
and the plan holds what is valid. Fields depend on each other the way the commands make them:
a dropped fiducial or a locked set that is not valid unlocks the set (the operator re-confirms);
entry == target drops both points; a bad hand-eye or camera drops that calibration.

:class:`PlanStore` holds the session's current plan and commits a changed copy: saved first,
swapped in only once it is on disk, so the file and memory never disagree; a failed save leaves
both unchanged and says why in one line (``home_unwritable`` / ``plan_save_failed`` alarms).
"""

from __future__ import annotations

import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monotracker.engine.persistence import atomic_write_json, read_json
from monotracker.engine.plan import checks as pc
from monotracker.engine.plan.model import FORMAT, VERSION, Plan, PlanFiducial
from monotracker.errors import InputError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Rejection:
    """One field that was not restored: ``field`` (e.g. ``"fiducials[2]"``), ``reason`` (one line)."""

    field: str
    reason: str

    def __str__(self) -> str:
        return f"{self.field}: {self.reason}"


def restore_plan(d, min_usable: int = 4):
    """``(Plan, [Rejection])`` from a parsed plan file. Raises ``ValueError`` only when ``d`` is
    not a MonoTracker plan at all (wrong format marker, newer version)."""
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise ValueError("not a MonoTracker plan file")
    ver = d.get("version", -1)
    if isinstance(ver, bool) or not isinstance(ver, int):
        raise ValueError(f"plan version must be an integer, not {ver!r}")
    if ver > VERSION:
        raise ValueError(f"plan version {ver} is newer than this program ({VERSION})")
    rej: list[Rejection] = []
    plan = Plan()

    rev = d.get("revision", 0)
    if isinstance(rev, bool) or not isinstance(rev, int) or rev < 0:
        rej.append(Rejection("revision", f"must be a non-negative integer, not {rev!r}"))
    else:
        plan.revision = rev

    ct = d.get("ct_path")
    if ct is not None and not isinstance(ct, str):
        rej.append(Rejection("ct_path", f"must be a path string, not {type(ct).__name__}"))
    else:
        plan.ct_path = ct

    # ------------------------------------------------------------ fiducials
    fids_raw = d.get("fiducials", [])
    fids_ok = True
    if not isinstance(fids_raw, list):
        rej.append(Rejection("fiducials", f"must be a list, not {type(fids_raw).__name__}"))
        fids_raw, fids_ok = [], False
    for i, f in enumerate(fids_raw):
        if not isinstance(f, dict):
            rej.append(Rejection(f"fiducials[{i}]", f"must be an object, not {type(f).__name__}"))
            fids_ok = False
            continue
        why = pc.check_fiducial(f.get("id"), f.get("centre_lps_mm"), f.get("radius_mm"), f.get("score", 0.0),
                                f.get("status", "detected"))
        verified = f.get("verified")
        if why is None and verified is not None and not isinstance(verified, bool):
            why = f"fiducial {f.get('id')} verified must be true, false or null, not {verified!r}"
        role = f.get("role", "registration")
        why = why or pc.check_role(f.get("id"), role)
        if why:
            rej.append(Rejection(f"fiducials[{i}]", why))
            fids_ok = False
            continue
        plan.fiducials.append(PlanFiducial(int(f["id"]), np.asarray(f["centre_lps_mm"], float),
                                           float(f["radius_mm"]), float(f.get("score", 0.0)),
                                           f.get("status", "detected"), verified, role))
    why = pc.check_fiducial_set(plan.fiducials)
    if why:
        rej.append(Rejection("fiducials", why))
        plan.fiducials, fids_ok = [], False

    locked = d.get("fiducials_locked", False)
    if not isinstance(locked, bool):
        rej.append(Rejection("fiducials_locked", f"must be true or false, not {locked!r}"))
        locked = False
    elif locked and not fids_ok:
        rej.append(Rejection("fiducials_locked", "the locked fiducial set was not restored whole; confirm it again"))
        locked = False
    plan.fiducials_locked = locked
    if locked:
        why = pc.check_locked(plan, min_usable)
        if why:
            rej.append(Rejection("fiducials_locked", why))
            plan.fiducials_locked = False

    # ------------------------------------------------------------ path
    pts = {}
    for name in ("entry_lps_mm", "target_lps_mm"):
        v = d.get(name)
        if v is None:
            continue
        a, why = pc.check_point(v, name.split("_")[0])
        if why:
            rej.append(Rejection(name, why))
        else:
            pts[name] = a
    why = pc.check_entry_target_pair(pts.get("entry_lps_mm"), pts.get("target_lps_mm"))
    if why:
        rej.append(Rejection("entry_lps_mm/target_lps_mm", why))
        pts = {}
    plan.entry_lps_mm, plan.target_lps_mm = pts.get("entry_lps_mm"), pts.get("target_lps_mm")
    if plan.path_complete:
        why = pc.check_path(plan.entry_lps_mm, plan.target_lps_mm, plan.fiducials, None)
        if why:
            rej.append(Rejection("entry_lps_mm/target_lps_mm", why))
            plan.entry_lps_mm = plan.target_lps_mm = None

    # ------------------------------------------------------------ camera
    cam = d.get("camera")
    if cam is None:
        cam = {}
    if not isinstance(cam, dict):
        rej.append(Rejection("camera", f"must be an object, not {type(cam).__name__}"))
        cam = {}
    src, calib = cam.get("source"), cam.get("calibration_path")
    if src is not None and not isinstance(src, str):
        rej.append(Rejection("camera.source", f"must be a string, not {type(src).__name__}"))
        src = None
    if calib is not None and not isinstance(calib, str):
        rej.append(Rejection("camera.calibration_path", f"must be a path string, not {type(calib).__name__}"))
        calib = None
    K, dist, size = cam.get("K"), cam.get("dist"), cam.get("image_size")
    if isinstance(size, list):
        size = tuple(size)
    why = pc.check_camera(K, dist, size)
    if why:
        rej.append(Rejection("camera", why))
    else:
        plan.camera_source, plan.calibration_path = src, calib
        plan.K = None if K is None else np.asarray(K, float)
        plan.dist = None if dist is None else np.asarray(dist, float).ravel()
        plan.image_size = None if size is None else tuple(int(v) for v in size)

    # ------------------------------------------------------------ hand-eye
    T = d.get("T_base_cam_mm")
    if T is not None:
        why = pc.check_hand_eye(T)
        if why:
            rej.append(Rejection("T_base_cam_mm", why))
        else:
            plan.T_base_cam = np.asarray(T, float)

    # ------------------------------------------------------------ fiducial kit (the ct package's own checks)
    kit = d.get("fiducial_kit")
    if kit is not None:
        try:
            from monotracker.ct.kit import FiducialKit

            plan.fiducial_kit = FiducialKit.from_dict(kit)
        except (TypeError, ValueError) as exc:
            rej.append(Rejection("fiducial_kit", str(exc)))

    # ------------------------------------------------------------ the balls' finish (vision's vocabulary)
    finish = d.get("ball_finish")
    if finish is not None:
        why = pc.check_ball_finish(finish)
        if why:
            rej.append(Rejection("ball_finish", why))
        else:
            plan.ball_finish = str(finish)

    # ------------------------------------------------------------ integrity record (checked by the session)
    integ = d.get("integrity")
    if integ is not None:
        if isinstance(integ, dict) and all(isinstance(v, (str, type(None))) for v in integ.values()):
            plan.integrity = dict(integ)
        else:
            rej.append(Rejection("integrity", "must be an object of hash strings"))
    return plan, rej


@dataclass
class SavedPlan:
    """What :func:`load_saved_plan` found: the ``plan`` to start from, ``alarms`` as
    ``(code, message, data)`` to raise, ``reconfirm`` reasons the operator must re-confirm the
    plan for before arming, ``kept_aside`` (the copy of the original file, or None), the
    ``rejected`` fields, ``outside``: the file was changed outside the app and ``plan`` is the
    app's own last plan (or empty), which the caller saves back; ``interrupted``: the file is the
    plan before the last recorded save (a save cut short), used as it is."""

    plan: object
    alarms: list
    reconfirm: list
    kept_aside: object = None
    rejected: tuple = ()
    outside: bool = False
    interrupted: bool = False
    sha256: str | None = None  # the file's content digest (integrity.plan_content_sha256)


def _keep_aside(path, kind: str):
    """Copy ``path`` to ``plan.<kind>-<UTC timestamp>.json`` beside it; the copy's path or None."""
    import shutil
    import time

    path = Path(path)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    keep = path.with_name(f"plan.{kind}-{stamp}.json")
    n = 1
    while keep.exists():
        keep = path.with_name(f"plan.{kind}-{stamp}-{n}.json")
        n += 1
    try:
        shutil.copy2(path, keep)
    except OSError:
        return None
    return keep


def _has_content(plan) -> bool:
    return bool(plan.fiducials or plan.path_complete or plan.T_base_cam is not None)


def load_saved_plan(path, min_usable: int, last_saved: dict | None = None, key=None) -> SavedPlan:
    """Read ``plan.json`` at start-up; never raises. An unreadable file, or one with invalid
    fields, is copied aside (``plan.unreadable-*`` / ``plan.rejected-*``) and named in an alarm;
    the plan holds what is valid (or is empty).

    Whether the file is the app's own (:func:`~monotracker.engine.integrity.judge_saved_plan`):
    ``last_saved`` is the audit chain's newest ``plan_saved`` row (its data), ``key`` this
    machine's :class:`~monotracker.engine.integrity.IntegrityKey`. A file that is not (changed
    outside the app, its content hash recomputed or not) is copied aside as
    ``plan.changed-outside-*``; the app's last plan from the audit chain is the plan (else an empty
    one), with a ``plan_changed_outside`` alarm naming the differences and a re-confirmation
    before arming. A file neither can judge (an older version's) falls back to its unkeyed
    content hash: one that does not match asks for re-confirmation."""
    from monotracker.engine.integrity import judge_saved_plan, plan_content_sha256, plan_stamp_problem, summarise_changes

    try:
        raw = read_json(path)
        plan, rejected = restore_plan(raw, min_usable)
    except (OSError, ValueError, RecursionError) as exc:
        keep = _keep_aside(path, "unreadable")
        where = f"kept as {keep.name}" if keep else "could not be copied aside"
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return SavedPlan(Plan(), [("plan_unreadable", f"saved plan could not be read ({msg}); {where}, starting empty",
                                   {"kept_as": None if keep is None else str(keep)})], [], keep)
    alarms, reconfirm, keep = [], [], None
    if rejected:
        keep = _keep_aside(path, "rejected")
        where = f"original kept as {keep.name}" if keep else "original could not be copied aside"
        names = ", ".join(r.field for r in rejected)
        alarms.append(("plan_field_rejected",
                       f"saved plan: {names} not restored ({rejected[0].reason}); {where}",
                       {"rejected": [{"field": r.field, "reason": r.reason} for r in rejected],
                        "kept_as": None if keep is None else str(keep)}))
    verdict = judge_saved_plan(raw, last_saved, key)
    sha = plan_content_sha256(raw)
    if verdict is not None and not verdict.ok:
        return _changed_outside(path, verdict, min_usable, alarms, keep, rejected, summarise_changes)
    stamp = plan_stamp_problem(raw) if verdict is None else None
    if stamp is not None and _has_content(plan):
        alarms.append(("plan_changed_outside", f"{stamp}; re-confirm the plan before arming", {}))
        reconfirm.append(stamp)
    pending = plan.integrity.get("reconfirm_pending")
    if pending and stamp is None:
        alarms.append(("plan_reconfirm_pending", f"{pending}; re-confirm the plan before arming", {}))
        reconfirm.append(pending)
    return SavedPlan(plan, alarms, reconfirm, keep, tuple(rejected),
                     interrupted=verdict is not None and verdict.interrupted, sha256=sha)


def _changed_outside(path, verdict, min_usable, alarms, keep, rejected, summarise_changes) -> SavedPlan:
    """The file is not the app's own: keep it aside, start from the app's last plan (or empty)."""
    aside = _keep_aside(path, "changed-outside")
    where = f"the edited file is kept as {aside.name}" if aside else "the edited file could not be copied aside"
    plan = Plan()
    if verdict.app_plan is not None:
        try:
            plan, _ = restore_plan(verdict.app_plan, min_usable)
        except ValueError:  # never expected: the app wrote it
            plan = Plan()
    if _has_content(plan):
        restored = f"the app's last plan (revision {plan.revision}) is restored"
    elif verdict.app_plan is not None:
        restored = "the app's last plan (empty) is restored"
    else:
        restored = "no earlier plan of the app to restore: starting empty"
    what = summarise_changes(list(verdict.changes)) if verdict.changes else ""
    head = f"plan.json was changed outside the app ({verdict.how})" + (f": {what}" if what else "")
    line = f"{head}; {restored}; {where}"
    need = _has_content(plan)
    alarms.append(("plan_changed_outside", line + ("; re-confirm the plan before arming" if need else ""),
                   {"changes": list(verdict.changes), "how": verdict.how, "kept_as": None if aside is None else str(aside),
                    "restored_revision": plan.revision if verdict.app_plan is not None else None}))
    reconfirm = [f"{head}; the app's last plan was restored"] if need else []
    return SavedPlan(plan, alarms, reconfirm, aside or keep, tuple(rejected), outside=True)


def plan_from_dict(d: dict, min_usable: int = 3) -> Plan:
    """Parse a saved plan strictly: raises ``ValueError`` with a one-line reason naming the first
    field that fails its check (the session restores field by field instead)."""
    plan, rejected = restore_plan(d, min_usable)
    if rejected:
        raise ValueError(str(rejected[0]))
    return plan


def load_plan(path) -> Plan:
    """Load ``path`` strictly; raises ``OSError`` or ``ValueError`` (one line) if unusable."""
    return plan_from_dict(read_json(path))


def prepare_home(home: Path) -> None:
    """Create the session folder; :class:`InputError` (one line) when ``home`` cannot be one."""
    if home.exists() and not home.is_dir():
        raise InputError(f"session folder {home} is not a folder")
    try:
        home.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the session folder {home}: {exc.strerror or exc}") from None


def home_write_problem(home: Path) -> str | None:
    """None when a file can be created in ``home``; else the reason (one line)."""
    try:
        with tempfile.NamedTemporaryFile(dir=home, prefix=".write-check-"):
            pass
    except OSError as exc:
        return exc.strerror or str(exc)
    return None


class PlanStore:
    """The session's current plan and its file (``path``, in the session folder ``home``).

    ``plan`` is read and replaced only under the session's state lock (the editor's
    transactions hold it). ``home_unwritable``: the last save failure while the folder is not
    writable (None once a save succeeds again). ``events``: the event bus for the alarms.
    ``audit``: the session's :class:`~monotracker.engine.audit.AuditLog` (None: library use, no
    ``plan_saved`` rows). ``saved_sha``: the content digest of the plan on disk (None: none yet)."""

    def __init__(self, path: Path, home: Path, events, audit=None):
        self.path = Path(path)
        self.home = Path(home)
        self.plan = Plan()
        self.home_unwritable: str | None = None
        self.saved_sha: str | None = None
        self._events = events
        self._audit = audit

    def commit(self, plan: Plan, why: str) -> str | None:
        """Save ``plan`` (a modified copy) and only then make it the current plan; the caller holds
        the lock. Returns None when saved and swapped in, else a one-line reason (memory unchanged,
        a ``home_unwritable`` alarm stands until a save succeeds again).

        With an audit log the save first writes a ``plan_saved`` row (the plan, its content digest
        and the digest of the plan it replaces) durably (committed or spilled with fsync): a
        ``kill -9`` between the row and the file leaves the file one save behind its row, which the
        restore recognises (:func:`~monotracker.engine.integrity.judge_saved_plan`); never a plan
        on disk that the audit chain does not know. No row, no save."""
        from monotracker.engine.integrity import plan_content_sha256

        plan.revision = self.plan.revision + 1
        d = plan.to_dict()
        sha = plan_content_sha256(d)
        if self._audit is not None:
            ok = self._audit.record_durable("event", "info", "plan_saved", f"plan saved (revision {plan.revision}): {why}",
                                            {"plan": d, "plan_sha256": sha, "previous_sha256": self.saved_sha,
                                             "revision": plan.revision, "why": why})
            if not ok:
                reason = "not saved (the audit log could not record the change): the plan on disk and in memory are unchanged"
                self._events.alert("alarm", "plan_save_failed", f"{why}: {reason}", {"why": why})
                return reason
        try:
            atomic_write_json(self.path, d)
        except OSError as exc:
            reason = f"not saved ({exc.strerror or exc}): the plan on disk and in memory are unchanged"
            if self._audit is not None:  # the chain's last plan is the one still on disk
                self._audit.record("event", "info", "plan_saved", f"plan not saved ({why}): the plan on disk is unchanged",
                                   {"plan": self.plan.to_dict(), "plan_sha256": self.saved_sha, "previous_sha256": sha,
                                    "revision": self.plan.revision, "why": f"save failed: {why}"})
            if self.home_unwritable is None:
                self._events.alert("alarm", "home_unwritable", f"cannot write the session folder {self.home}: "
                                   f"{exc.strerror or exc}; changes are refused until it is writable",
                                   {"why": why, "errno": getattr(exc, "errno", None)})
            self._events.alert("alarm", "plan_save_failed", f"{why}: {reason}", {"why": why})
            self.home_unwritable = str(exc)
            return reason
        self.plan = plan
        self.saved_sha = sha
        if self.home_unwritable is not None:
            self.home_unwritable = None
            self._events.alert("info", "home_writable", f"session folder {self.home} is writable again")
        log.debug("plan saved (%s) revision %d", why, plan.revision)
        return None
