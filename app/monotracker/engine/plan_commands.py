"""The plan's commands and its integrity, as a part of :class:`~monotracker.engine.Session`.

Every way plan state enters goes through :mod:`monotracker.engine.plan_checks` here: the editing
commands (fiducials, entry/target, hand-eye, the camera the loop stores), the restore of
``plan.json`` (:mod:`monotracker.engine.plan_restore`) and the arming gate
(:meth:`PlanCommands.plan_not_ready`). Each command builds the new plan on a copy, saves it, and
only then swaps it in (:meth:`PlanCommands._commit_plan_locked`): a save that fails leaves memory
and disk unchanged and the command says why in one line.

:class:`PlanCommands` is a mixin: it uses the session's ``_lock``, ``_plan``, ``_plan_path``,
``_bus``, ``_loop``, ``_anatomy``, ``_ct``, ``_ct_sha256``, ``_reconfirm``, ``_home_unwritable``,
``home`` and ``config``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from monotracker.engine import plan_checks
from monotracker.engine.plan import Plan, PlanFiducial
from monotracker.engine.snapshot import CommandResult
from monotracker.errors import InputError

log = logging.getLogger(__name__)


def _prepare_home(home: Path) -> None:
    """Create the session folder; :class:`InputError` (one line) when ``home`` cannot be one."""
    if home.exists() and not home.is_dir():
        raise InputError(f"session folder {home} is not a folder")
    try:
        home.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the session folder {home}: {exc.strerror or exc}") from None


def _home_write_problem(home: Path) -> str | None:
    """None when a file can be created in ``home``; else the reason (one line)."""
    import tempfile

    try:
        with tempfile.NamedTemporaryFile(dir=home, prefix=".write-check-"):
            pass
    except OSError as exc:
        return exc.strerror or str(exc)
    return None


def _ok(msg: str = "") -> CommandResult:
    return CommandResult(True, msg)


def _fail(msg: str) -> CommandResult:
    return CommandResult(False, msg)


def _point3(p) -> np.ndarray:
    """(3,) LPS mm from any 3-sequence; :class:`InputError` (one line) unless :func:`plan_checks.check_point` passes."""
    try:
        a = np.asarray(p, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError("a point needs three finite coordinates (LPS mm)") from None
    a, why = plan_checks.check_point(a, "the point")
    if why:
        raise InputError(f"{why} (a point needs three finite coordinates, LPS mm)")
    return a


class PlanCommands:
    """Plan editing, restore, integrity and readiness (mixed into ``Session``)."""

    # ================================================================== plan persistence
    def _restore_plan(self) -> None:
        """Restore ``plan.json`` field by field with the commands' checks (never raises)."""
        if not self._plan_path.exists():
            return
        from monotracker.engine.plan_restore import load_saved_plan

        saved = load_saved_plan(self._plan_path, self.config.min_fiducials)
        self._plan = saved.plan
        self._reconfirm = list(saved.reconfirm)
        codes = [c for c, _, _ in saved.alarms]
        for code, msg, data in saved.alarms:
            if code == "plan_field_rejected":  # stands until a new plan (the rest derive from the state)
                self._alarm_board.set(code, msg, float(self.clock()))
            self._bus.alert("alarm", code, msg, data)
        if saved.rejected:
            # the file on disk would say what memory does not: write what was restored (the original
            # is aside), carrying the pending re-confirmation so a restart cannot forget it
            with self._lock:
                plan = self._plan.copy()
                if self._reconfirm:
                    plan.integrity["reconfirm_pending"] = self._reconfirm[0]
                self._commit_plan_locked(plan, "restored plan (invalid fields removed)")
        if "plan_unreadable" in codes:
            with self._lock:
                self._commit_plan_locked(Plan(), "empty plan (the unreadable one is kept aside)")
            return
        plan = self._plan
        self._bus.event("plan_restored", f"plan restored (revision {plan.revision}, "
                        f"{len(plan.usable_fiducials())} fiducials, path {'set' if plan.path_complete else 'not set'})",
                        {"revision": plan.revision, "plan": plan.to_dict()})

    def _commit_plan_locked(self, plan: Plan, why: str) -> str | None:
        """Save ``plan`` (a modified copy) and only then make it the session's plan; caller holds
        the lock. Returns None when saved and swapped in, else a one-line reason (memory unchanged,
        a ``home_unwritable`` alarm stands until a save succeeds again)."""
        plan.revision = self._plan.revision + 1
        try:
            plan.save(self._plan_path)
        except OSError as exc:
            reason = f"not saved ({exc.strerror or exc}): the plan on disk and in memory are unchanged"
            if self._home_unwritable is None:
                self._bus.alert("alarm", "home_unwritable", f"cannot write the session folder {self.home}: "
                                f"{exc.strerror or exc}; changes are refused until it is writable",
                                {"why": why, "errno": getattr(exc, "errno", None)})
            self._bus.alert("alarm", "plan_save_failed", f"{why}: {reason}", {"why": why})
            self._home_unwritable = str(exc)
            return reason
        self._plan = plan
        if self._home_unwritable is not None:
            self._home_unwritable = None
            self._bus.alert("info", "home_writable", f"session folder {self.home} is writable again")
        log.debug("plan saved (%s) revision %d", why, plan.revision)
        return None

    def plan_not_ready(self) -> str | None:
        """Why the current plan cannot be armed or tracked on (one line), or None when it is a
        complete plan that passes every check (:func:`plan_checks.plan_problems`), its CT is loaded
        when it was made on one, and no re-confirmation is pending."""
        with self._lock:
            plan, anatomy, reconfirm = self._plan, self._anatomy, list(self._reconfirm)
            problems = plan_checks.plan_problems(plan, self.config.min_fiducials, anatomy)
            ct_wanted = plan.ct_path is not None and self._ct is None
        if problems:
            return problems[0]
        if ct_wanted:
            return "the plan's CT is not loaded, so the path cannot be checked against it; load it first"
        if reconfirm:
            return f"re-confirm the plan first: {reconfirm[0]}"
        return None

    def reconfirm_plan(self) -> CommandResult:
        """The operator has reviewed the plan after an integrity alarm (edited outside the app,
        changed CT or calibration): clear the pending re-confirmation and record the plan's
        current hashes. Refused when the plan itself fails its checks (the reason is returned)."""
        with self._lock:
            if not self._reconfirm:
                return _ok("nothing to re-confirm")
            problems = plan_checks.plan_problems(self._plan, self.config.min_fiducials, self._anatomy)
            if problems:
                return _fail(f"the plan cannot be re-confirmed: {problems[0]}")
            reasons, plan = list(self._reconfirm), self._plan.copy()
            plan.integrity.pop("reconfirm_pending", None)
            if self._ct is not None and self._ct_sha256:
                plan.integrity["ct_sha256"] = self._ct_sha256
            err = self._commit_plan_locked(plan, "plan re-confirmed")
            if err:
                return _fail(err)
            self._reconfirm = []
        self._bus.event("plan_reconfirmed", "plan re-confirmed by the operator", {"reasons": reasons})
        return _ok("plan re-confirmed")

    def integrity_alarms(self) -> list[tuple[str, str]]:
        """Integrity conditions that stand until they clear, as ``(code, one line)``, most serious
        first: the session folder is unwritable, the plan needs re-confirmation, the plan's CT is
        missing, audit rows were lost or are delayed. For the active-alarm list (``snap.alarms``);
        each was also raised once as an alert when it began."""
        out = []
        with self._lock:
            unwritable, reconfirm, ct_path = self._home_unwritable, list(self._reconfirm), self._plan.ct_path
        if unwritable:
            out.append(("home_unwritable", f"session folder {self.home} is not writable ({unwritable}): "
                        "plan changes are refused"))
        if reconfirm:
            out.append(("plan_reconfirm_pending", f"re-confirm the plan: {reconfirm[0]}"))
        if ct_path and not Path(ct_path).exists():
            out.append(("plan_ct_missing", f"the plan's CT {ct_path} is missing"))
        audit = self._audit
        if audit.tampered:
            out.append(("audit_tampered", f"audit log {audit.path.name}: {audit.tampered}"))
        if audit.lost:
            out.append(("audit_lost", f"{audit.lost} audit rows were lost"))
        elif audit.open_error or getattr(audit, "_trouble", False):
            out.append(("audit_delayed", f"audit rows are delayed to {audit.spill_path} ({audit.delayed} so far)"))
        key = audit.key
        if key is not None and key.problem:
            out.append(("integrity_key_unavailable", f"{key.problem}: changes outside the app are seen through "
                        "the audit chain only"))
        return out

    def _need_reconfirm(self, code: str, reason: str, data: dict | None = None) -> None:
        with self._lock:
            self._reconfirm.append(reason)
        self._bus.alert("alarm", code, f"{reason}; re-confirm the plan before arming", data)

    # ================================================================== fiducials
    def set_fiducial_status(self, fid_id: int, status: str) -> CommandResult:
        """Operator decision on one fiducial.

        ``fid_id``: the fiducial's id (int, as in ``snap.fiducials``). ``status``: ``"confirmed" |
        "rejected" | "detected"`` (undo). Refused while the set is locked, for an unknown id, to set
        an added fiducial back to detected, or when the plan cannot be saved (nothing changes)."""
        if status not in ("confirmed", "rejected", "detected"):
            return _fail(f"status must be confirmed, rejected or detected, not {status!r}")
        if isinstance(fid_id, bool) or not isinstance(fid_id, (int, np.integer)):
            return _fail(f"fiducial id must be an integer, not {fid_id!r}")
        with self._lock:
            if self._plan.fiducials_locked:
                return _fail("fiducials are locked; unlock them first")
            plan = self._plan.copy()
            f = plan.fiducial(int(fid_id))
            if f is None:
                return _fail(f"no fiducial with id {fid_id}")
            if f.status == "added" and status == "detected":
                return _fail("an added fiducial can be confirmed or rejected, not set to detected")
            old, f.status = f.status, status
            why = plan_checks.check_fiducial_set(plan.fiducials)
            if why:
                return _fail(why)
            err = self._commit_plan_locked(plan, "fiducial status")
            if err:
                return _fail(err)
            centre = f.centre_lps_mm.tolist()
        self._bus.event(f"fiducial_{status}", f"fiducial {fid_id} {status} (was {old})",
                        {"id": int(fid_id), "centre_lps_mm": centre, "previous": old})
        return _ok(f"fiducial {fid_id} {status}")

    def add_fiducial(self, p_lps_mm, radius_mm: float | None = None, manual: bool = False) -> CommandResult:
        """Add an operator-picked fiducial; it counts as confirmed (status ``"added"``).

        ``p_lps_mm``: ball centre, (3,) CT LPS mm, finite. ``radius_mm``: ball radius in mm
        (default: the median of the plan's fiducials, else 4 mm; within ``PlanLimits.radius_mm``).
        With a CT loaded, the CT must show a dense ball of that radius there
        (:func:`plan_checks.check_added_fiducial`), else the command is refused with what the CT
        reads; ``manual=True`` adds it anyway, marked "manual, unverified" with a warning. Without a
        CT it is added unverified with a warning. Refused while the set is locked, when it overlaps
        another fiducial, or when the plan cannot be saved (nothing changes)."""
        try:
            p = _point3(p_lps_mm)
        except InputError as exc:
            return _fail(str(exc))
        with self._lock:
            if self._plan.fiducials_locked:
                return _fail("fiducials are locked; unlock them first")
            radii = [f.radius_mm for f in self._plan.fiducials]
            if radius_mm is not None:
                r, why = plan_checks.real_number(radius_mm, "fiducial radius")
                if why:
                    return _fail(why)
            else:
                r = float(np.median(radii)) if radii else 4.0
            lo, hi = plan_checks.LIMITS.radius_mm
            if not (lo <= r <= hi):
                return _fail(f"fiducial radius must be between {lo:g} and {hi:g} mm, not {r:g}")
            for f in self._plan.fiducials:
                if f.status != "rejected" and np.linalg.norm(f.centre_lps_mm - p) < 2 * r:
                    return _fail(f"too close to fiducial {f.id} ({np.linalg.norm(f.centre_lps_mm - p):.1f} mm)")
            verified, how = plan_checks.check_added_fiducial(self._anatomy, p, r)
            if verified is False and not manual:
                return _fail(f"{how}; pick the ball's centre, or add it as manual (unverified)")
            fid = max((f.id for f in self._plan.fiducials), default=-1) + 1
            plan = self._plan.copy()
            plan.fiducials.append(PlanFiducial(fid, p, r, 1.0, "added", bool(verified)))
            err = self._commit_plan_locked(plan, "fiducial added")
            if err:
                return _fail(err)
        self._bus.event("fiducial_added", f"fiducial {fid} added by the operator", {"id": fid, "centre_lps_mm": p.tolist(),
                                                                                    "radius_mm": r, "verified": verified,
                                                                                    "check": how})
        if not verified:
            self._bus.alert("warning", "fiducial_unverified", f"fiducial {fid} added manual, unverified: {how}",
                            {"id": fid})
            return _ok(f"fiducial {fid} added (manual, unverified: {how})")
        return _ok(f"fiducial {fid} added")

    def confirm_fiducials(self) -> CommandResult:
        """Lock the fiducial set: needs >= ``config.min_fiducials`` confirmed or added fiducials,
        each passing its check, no two overlapping. Refused (nothing changes) when the plan cannot be saved."""
        with self._lock:
            if self._plan.fiducials_locked:
                return _ok("fiducials already locked")
            n = len(self._plan.usable_fiducials())
            need = self.config.min_fiducials
            if n < need:
                return _fail(f"{n} fiducials confirmed; at least {need} are needed")
            plan = self._plan.copy()
            plan.fiducials_locked = True
            for f in plan.usable_fiducials():
                why = plan_checks.check_fiducial(f.id, f.centre_lps_mm, f.radius_mm, f.score, f.status)
                if why:
                    return _fail(why)
            why = plan_checks.check_fiducial_set(plan.fiducials) or plan_checks.check_locked(plan, need)
            if why:
                return _fail(why)
            err = self._commit_plan_locked(plan, "fiducials locked")
            if err:
                return _fail(err)
            ids = [f.id for f in plan.usable_fiducials()]
        self._bus.event("fiducials_locked", f"fiducial set locked ({n} fiducials: {ids})", {"ids": ids})
        return _ok(f"{n} fiducials locked")

    def set_fiducial_role(self, fid_id: int, role: str) -> CommandResult:
        """Give fiducial ``fid_id`` the role ``"registration"`` (used in the fit, the default) or
        ``"validation"`` (seen by the camera but kept out of the fit, to verify it: see
        ``engine/verification.py``). At least ``config.min_fiducials`` usable fiducials must keep the
        registration role. Refused while the fiducials are locked, or when the plan cannot be saved."""
        why = plan_checks.check_role(fid_id, role)
        if why:
            return _fail(why)
        with self._lock:
            if self._plan.fiducials_locked:
                return _fail("fiducials are locked; unlock them first")
            plan = self._plan.copy()
            f = plan.fiducial(int(fid_id))
            if f is None:
                return _fail(f"no fiducial with id {fid_id}")
            old, f.role = f.role, role
            left = len(plan.registration_fiducials())
            if role == "validation" and left < self.config.min_fiducials:
                return _fail(f"only {left} fiducials would remain for the registration; "
                             f"at least {self.config.min_fiducials} are needed")
            err = self._commit_plan_locked(plan, "fiducial role")
            if err:
                return _fail(err)
        self._bus.event("fiducial_role", f"fiducial {fid_id}: {role} (was {old})",
                        {"id": int(fid_id), "role": role, "previous": old})
        return _ok(f"fiducial {fid_id}: {role}")

    def unlock_fiducials(self) -> CommandResult:
        """Back to editing the fiducials (refused while armed or tracking, or when the plan cannot be saved)."""
        if self._loop.robot_state() not in ("disarmed", "estopped"):
            return _fail("disarm the robot before editing fiducials")
        with self._lock:
            if not self._plan.fiducials_locked:
                return _ok("fiducials not locked")
            plan = self._plan.copy()
            plan.fiducials_locked = False
            err = self._commit_plan_locked(plan, "fiducials unlocked")
            if err:
                return _fail(err)
        self._bus.event("fiducials_unlocked", "fiducial set unlocked for editing")
        self._loop.plan_changed("fiducials unlocked for editing", restart_camera=False)
        return _ok("fiducials unlocked")

    # ================================================================== path planning
    def set_entry(self, p_lps_mm) -> CommandResult:
        """Set the needle's entry point: ``p_lps_mm`` (3,) CT LPS mm, finite. Refused while tracking,
        before the fiducials are locked, and when the path fails :func:`plan_checks.check_path`
        (with a CT: the entry within ``PlanLimits.entry_skin_mm`` of the skin; always: distinct
        from the target, length in range, clear of the fiducials), or the plan cannot be saved."""
        return self._set_path_point("entry", p_lps_mm)

    def set_target(self, p_lps_mm) -> CommandResult:
        """Set the target point: ``p_lps_mm`` (3,) CT LPS mm, finite. Refused like :meth:`set_entry`;
        with a CT the target must lie inside the CT volume and inside the head."""
        return self._set_path_point("target", p_lps_mm)

    def use_sample_plan(self) -> CommandResult:
        """Entry/target of the phantom's sample plan (meant for the sample CT); refused like
        :meth:`set_entry` / :meth:`set_target` (the first refusal is returned)."""
        from monotracker.sim.phantom import default_phantom

        ph = default_phantom()
        r = self.set_entry(ph.sample_entry_lps)
        return self.set_target(ph.sample_target_lps) if r.ok else r

    def _set_path_point(self, which: str, p_lps_mm) -> CommandResult:
        try:
            p = _point3(p_lps_mm)
        except InputError as exc:
            return _fail(str(exc))
        if self._loop.robot_state() == "tracking":
            return _fail("stop tracking before changing the path")
        with self._lock:
            if not self._plan.fiducials_locked:
                return _fail("confirm the fiducials before planning the path")
            plan = self._plan.copy()
            old = getattr(plan, f"{which}_lps_mm")
            setattr(plan, f"{which}_lps_mm", p)
            why = self._point_problem(which, p, plan)
            if why:
                return _fail(why)
            err = self._commit_plan_locked(plan, f"{which} set")
            if err:
                return _fail(err)
        self._bus.event(f"{which}_set", f"{which} set to ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm LPS",
                        {"lps_mm": p.tolist(), "previous": None if old is None else old.tolist()})
        if old is None or not np.array_equal(old, p):
            self._loop.plan_changed(f"{which} changed", restart_camera=True)
        return _ok(f"{which} set")

    def _point_problem(self, which: str, p: np.ndarray, plan: Plan) -> str | None:
        """The checks of one path point (caller holds the lock): its own anatomy check, and the
        whole path's checks once both points are set."""
        a = self._anatomy
        if a is not None:
            why = (plan_checks.check_entry_anatomy(p, a) if which == "entry" else plan_checks.check_target_anatomy(p, a))
            if why:
                return why
        if plan.path_complete:
            return plan_checks.check_path(plan.entry_lps_mm, plan.target_lps_mm, plan.fiducials, a)
        return None

    def set_hand_eye(self, T_base_cam_mm) -> CommandResult:
        """Set the hand-eye transform and save it in the plan.

        ``T_base_cam_mm``: 4x4 ``T_base_cam`` (camera frame -> robot base frame), translation in mm.
        Refused (one line, nothing changes) unless :func:`plan_checks.check_hand_eye` passes (finite,
        orthonormal rotation with det +1, last row 0 0 0 1, camera within 3 m of the base), while
        tracking, or when the plan cannot be saved."""
        why = plan_checks.check_hand_eye(T_base_cam_mm)
        if why:
            return _fail(why)
        T = np.asarray(T_base_cam_mm, dtype=float)
        if self._loop.robot_state() == "tracking":
            return _fail("stop tracking before changing the hand-eye calibration")
        with self._lock:
            plan = self._plan.copy()
            plan.T_base_cam = T.copy()
            err = self._commit_plan_locked(plan, "hand-eye")
            if err:
                return _fail(err)
        self._bus.event("hand_eye_set", "hand-eye calibration T_base_cam set", {"T_base_cam_mm": T.tolist()})
        return _ok("hand-eye set")

    def _store_camera(self, source: str, calibration_path, K, dist, image_size) -> str | None:
        """Save the camera in use and its calibration in the plan (called by the loop when a camera
        starts). ``K`` 3x3 px, ``dist`` OpenCV coefficients, ``image_size`` (width, height) px.
        Returns None when stored (or unchanged), else why it was refused (:func:`plan_checks.check_camera`
        or the save failed). A calibration file whose content changed since the plan recorded it
        raises ``calibration_changed`` and asks for re-confirmation."""
        size = None if image_size is None else tuple(int(v) for v in image_size)
        why = plan_checks.check_camera(K, dist, size)
        if why:
            self._bus.alert("alarm", "camera_calibration_invalid", f"camera calibration refused: {why}")
            return why
        cal_sha = None
        if calibration_path:
            from monotracker.engine.integrity import content_sha256

            try:
                cal_sha = content_sha256(calibration_path)
            except OSError as exc:
                return f"calibration file {calibration_path} cannot be read ({exc.strerror or exc})"
        with self._lock:
            p = self._plan
            recorded = p.integrity.get("calibration_sha256")
            changed = (calibration_path and p.calibration_path == calibration_path and recorded
                       and cal_sha != recorded)
            same = (p.camera_source == source and p.calibration_path == calibration_path and p.K is not None
                    and K is not None and np.array_equal(p.K, K) and not changed)
            if same:
                return None
            plan = p.copy()
            plan.camera_source, plan.calibration_path = source, calibration_path
            plan.K = None if K is None else np.asarray(K, float).copy()
            plan.dist = None if dist is None else np.asarray(dist, float).ravel().copy()
            plan.image_size = size
            if cal_sha:
                plan.integrity["calibration_sha256"] = cal_sha
            else:
                plan.integrity.pop("calibration_sha256", None)
            err = self._commit_plan_locked(plan, "camera calibration")
            if err:
                return err
        if changed:
            self._need_reconfirm("calibration_changed", f"the calibration file {calibration_path} changed since "
                                 "the plan recorded it (content hash differs)", {"path": calibration_path})
        self._bus.event("camera_calibration", f"camera {source}: calibration stored in the plan",
                        {"source": source, "calibration_path": calibration_path,
                         "K": None if K is None else np.asarray(K).tolist(),
                         "dist": None if dist is None else np.asarray(dist).ravel().tolist(),
                         "image_size": None if image_size is None else list(image_size)})
        return None
