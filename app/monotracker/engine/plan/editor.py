"""The plan's commands: fiducials, path, hand-eye, the camera in use, re-confirmation, restore.

Every way plan state enters goes through :mod:`~monotracker.engine.plan.checks` here: the editing
commands, the camera the loop stores, the restore of ``plan.json``
(:mod:`~monotracker.engine.plan.store`) and the arming gate (:meth:`PlanEditor.plan_not_ready`).
Each command is one :meth:`PlanEditor.edit` transaction: it changes a copy of the plan under the
session's state lock; on a clean exit the copy is saved and only then swapped in
(:meth:`~monotracker.engine.plan.store.PlanStore.commit`); raising :class:`Refused` (or a failed
save) leaves memory and disk unchanged and the command says why in one line.

Arming is consent to one plan: the path and the hand-eye are refused while the robot is armed,
tracking or holding (:data:`ENGAGED_REFUSAL`), and any other revision that reaches an engaged
robot disarms it first (``disarm_for_revision(why)``, the robot part's ``plan_changed_armed``
alarm): the arm never moves onto a plan it was not armed for.

The editor's collaborators, given by the session: the :class:`~.store.PlanStore`, the state lock,
the event bus and alarm board, the session clock (s), the configuration, ``ct()`` (the loaded CT's
facts: :class:`CTFacts`, or None), ``robot_state()`` and ``plan_changed(why, restart_camera)`` of
the tracking loop, ``forget_ct()`` (a new plan drops the CT), ``disarm_for_revision(why)`` (the
robot part: disarms an engaged robot before a plan revision is saved) and the audit log (its
newest ``plan_saved`` row says which plan the app saved last).
"""

from __future__ import annotations

import functools
import logging
from contextlib import contextmanager
from pathlib import Path
from typing import Protocol

import numpy as np

from monotracker.engine.plan import checks as plan_checks
from monotracker.engine.plan.model import Plan, PlanFiducial
from monotracker.engine.plan.store import load_saved_plan
from monotracker.engine.snapshot import CommandResult
from monotracker.errors import InputError

log = logging.getLogger(__name__)


#: the robot states in which the arm may move (it was armed for the plan as it is)
ENGAGED = ("armed", "tracking", "holding")
ENGAGED_REFUSAL = ("disarm the robot before changing the path (arming is for one plan: arm again with the PIN "
                   "after the change)")


class Refused(Exception):
    """A plan command refused (``str`` is the one line for the operator); nothing changed."""


class CTFacts(Protocol):
    """What the plan's checks need of the loaded CT (``engine/ct_job.py``'s ``LoadedCT``)."""

    anatomy: plan_checks.Anatomy
    sha256: str | None


def command(fn):
    """A plan command: :class:`Refused` becomes ``CommandResult(False, why)``."""

    @functools.wraps(fn)
    def run(*args, **kwargs) -> CommandResult:
        try:
            return fn(*args, **kwargs)
        except Refused as exc:
            return CommandResult.refused(str(exc))
    return run


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


class PlanEditor:
    """Plan editing, restore, integrity and readiness (see the module docstring)."""

    def __init__(self, store, *, lock, events, alarms, clock, config, ct, robot_state, plan_changed, forget_ct,
                 audit=None, disarm_for_revision=None):
        self.store = store
        self._lock = lock
        self._bus = events
        self._board = alarms
        self._clock = clock
        self._config = config
        self._ct = ct
        self._robot_state = robot_state
        self._plan_changed = plan_changed
        self._forget_ct = forget_ct
        self._audit = audit
        self._disarm_for_revision = disarm_for_revision
        self.reconfirm: list[str] = []  # why the operator must re-confirm the plan before arming

    # ================================================================== transaction
    @property
    def plan(self) -> Plan:
        """The current plan (read it under the state lock; never modify it: use :meth:`edit`)."""
        return self.store.plan

    def copy(self) -> Plan:
        """A deep copy of the current plan."""
        with self._lock:
            return self.store.plan.copy()

    @contextmanager
    def edit(self, why: str):
        """One plan change as a transaction: yields a copy of the plan to change (under the state
        lock); on a clean exit the copy is saved and only then made the plan. Raise :class:`Refused`
        inside to change nothing; a failed save raises :class:`Refused` with its reason."""
        with self._lock:
            draft = self.store.plan.copy()
            yield draft
            if self._disarm_for_revision is not None:  # never a new plan under an engaged arm
                self._disarm_for_revision(why)
            err = self.store.commit(draft, why)
            if err:
                raise Refused(err)
            if draft.ct_path or draft.fiducials or draft.path_complete:
                self._board.clear("plan_unreadable", float(self._clock()))  # a new plan is saved

    def _anatomy(self):
        ct = self._ct()
        return None if ct is None else ct.anatomy

    # ================================================================== restore
    def restore(self) -> None:
        """Restore ``plan.json`` field by field with the commands' checks (never raises). A file
        that is not the app's own (the audit chain's last ``plan_saved`` row, this machine's MAC:
        :func:`~monotracker.engine.plan.store.load_saved_plan`) is kept aside and the app's last
        plan is restored and saved back; ``plan_unreadable`` stands until a new plan is saved."""
        path = self.store.path
        if not path.exists():
            return
        last, problem = (None, None) if self._audit is None else self._audit.last_record("plan_saved")
        if problem:
            log.warning("plan restore: %s", problem)
        key = None if self._audit is None else self._audit.key
        saved = load_saved_plan(path, self._config.min_fiducials, last_saved=last, key=key)
        self.store.plan = saved.plan
        self.store.saved_sha = None if saved.outside else saved.sha256
        self.reconfirm = list(saved.reconfirm)
        codes = [c for c, _, _ in saved.alarms]
        for code, msg, data in saved.alarms:
            if code in ("plan_field_rejected", "plan_unreadable"):  # stand until a new plan (the rest derive
                self._board.set(code, msg, float(self._clock()))  # from the state)
            self._bus.alert("alarm", code, msg, data)
        if saved.rejected or saved.outside or saved.interrupted:
            # the file on disk would say what memory does not: write what was restored (the original
            # is aside), carrying the pending re-confirmation so a restart cannot forget it
            why = ("the app's last plan restored (plan.json was changed outside the app)" if saved.outside else
                   "restored plan (invalid fields removed)" if saved.rejected else
                   "the plan on disk kept (its last save was cut short)")
            with self._lock:
                plan = self.store.plan.copy()
                if self.reconfirm:
                    plan.integrity["reconfirm_pending"] = self.reconfirm[0]
                self.store.commit(plan, why)
        if "plan_unreadable" in codes:
            with self._lock:
                self.store.commit(Plan(), "empty plan (the unreadable one is kept aside)")
            return
        plan = self.store.plan
        self._bus.event("plan_restored", f"plan restored (revision {plan.revision}, "
                        f"{len(plan.usable_fiducials())} fiducials, path {'set' if plan.path_complete else 'not set'})",
                        {"revision": plan.revision, "plan": plan.to_dict(), "interrupted_save": saved.interrupted})

    # ================================================================== readiness and integrity
    def plan_not_ready(self) -> str | None:
        """Why the current plan cannot be armed or tracked on (one line), or None when it is a
        complete plan that passes every check (:func:`plan_checks.plan_problems`), its CT is loaded
        when it was made on one, and no re-confirmation is pending."""
        with self._lock:
            plan, ct, reconfirm = self.store.plan, self._ct(), list(self.reconfirm)
            problems = plan_checks.plan_problems(plan, self._config.min_fiducials, None if ct is None else ct.anatomy)
            ct_wanted = plan.ct_path is not None and ct is None
        if problems:
            return problems[0]
        if ct_wanted:
            return "the plan's CT is not loaded, so the path cannot be checked against it; load it first"
        if reconfirm:
            return f"re-confirm the plan first: {reconfirm[0]}"
        return None

    @command
    def reconfirm_plan(self) -> CommandResult:
        """The operator has reviewed the plan after an integrity alarm (edited outside the app,
        changed CT or calibration): clear the pending re-confirmation and record the plan's
        current hashes. Refused when the plan itself fails its checks (the reason is returned)."""
        with self._lock:
            if not self.reconfirm:
                return CommandResult.done("nothing to re-confirm")
            ct = self._ct()
            problems = plan_checks.plan_problems(self.store.plan, self._config.min_fiducials,
                                                 None if ct is None else ct.anatomy)
            if problems:
                raise Refused(f"the plan cannot be re-confirmed: {problems[0]}")
            reasons = list(self.reconfirm)
            with self.edit("plan re-confirmed") as plan:
                plan.integrity.pop("reconfirm_pending", None)
                if ct is not None and ct.sha256:
                    plan.integrity["ct_sha256"] = ct.sha256
            self.reconfirm = []
        self._bus.event("plan_reconfirmed", "plan re-confirmed by the operator", {"reasons": reasons})
        return CommandResult.done("plan re-confirmed")

    def integrity_alarms(self) -> list[tuple[str, str]]:
        """The plan's integrity conditions that stand until they clear, as ``(code, one line)``,
        most serious first: the session folder is unwritable, the plan needs re-confirmation, the
        plan's CT is missing."""
        out = []
        with self._lock:
            unwritable, reconfirm, ct_path = self.store.home_unwritable, list(self.reconfirm), self.store.plan.ct_path
        if unwritable:
            out.append(("home_unwritable", f"session folder {self.store.home} is not writable ({unwritable}): "
                        "plan changes are refused"))
        if reconfirm:
            out.append(("plan_reconfirm_pending", f"re-confirm the plan: {reconfirm[0]}"))
        if ct_path and not Path(ct_path).exists():
            out.append(("plan_ct_missing", f"the plan's CT {ct_path} is missing"))
        return out

    def need_reconfirm(self, code: str, reason: str, data: dict | None = None) -> None:
        """An integrity alarm ``code``: arming waits until the operator re-confirms the plan."""
        with self._lock:
            self.reconfirm.append(reason)
        self._bus.alert("alarm", code, f"{reason}; re-confirm the plan before arming", data)

    # ================================================================== a new plan
    @command
    def new_plan(self) -> CommandResult:
        """Forget CT, fiducials, path (calibrations are kept). Refused while armed."""
        if self._robot_state() not in ("disarmed", "estopped"):
            raise Refused("disarm the robot before starting a new plan")
        with self._lock:  # one transaction: a fresh plan keeping the calibrations, then the CT goes
            keep = self.store.plan
            integ = {k: v for k, v in keep.integrity.items() if k == "calibration_sha256"}
            fresh = Plan(camera_source=keep.camera_source, calibration_path=keep.calibration_path,
                         K=keep.K, dist=keep.dist, image_size=keep.image_size, T_base_cam=keep.T_base_cam,
                         integrity=integ)
            err = self.store.commit(fresh, "new plan")
            if err:
                raise Refused(err)
            self._forget_ct()
            self.reconfirm = []
        self._board.clear_all(("plan_field_rejected", "fiducial_moved", "plan_unreadable"), float(self._clock()))
        self._bus.event("plan_cleared", "new plan: CT, fiducials and path cleared")
        self._plan_changed("new plan", False)
        return CommandResult.done("new plan")

    # ================================================================== fiducials
    @command
    def set_fiducial_status(self, fid_id: int, status: str) -> CommandResult:
        """Operator decision on one fiducial.

        ``fid_id``: the fiducial's id (int, as in ``snap.fiducials``). ``status``: ``"confirmed" |
        "rejected" | "detected"`` (undo). Refused while the set is locked, for an unknown id, to set
        an added fiducial back to detected, or when the plan cannot be saved (nothing changes)."""
        if status not in ("confirmed", "rejected", "detected"):
            raise Refused(f"status must be confirmed, rejected or detected, not {status!r}")
        if isinstance(fid_id, bool) or not isinstance(fid_id, (int, np.integer)):
            raise Refused(f"fiducial id must be an integer, not {fid_id!r}")
        with self.edit("fiducial status") as plan:
            if plan.fiducials_locked:
                raise Refused("fiducials are locked; unlock them first")
            f = plan.fiducial(int(fid_id))
            if f is None:
                raise Refused(f"no fiducial with id {fid_id}")
            if f.status == "added" and status == "detected":
                raise Refused("an added fiducial can be confirmed or rejected, not set to detected")
            old, f.status = f.status, status
            why = plan_checks.check_fiducial_set(plan.fiducials)
            if why:
                raise Refused(why)
            centre = f.centre_lps_mm.tolist()
        self._bus.event(f"fiducial_{status}", f"fiducial {fid_id} {status} (was {old})",
                        {"id": int(fid_id), "centre_lps_mm": centre, "previous": old})
        return CommandResult.done(f"fiducial {fid_id} {status}")

    @command
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
            raise Refused(str(exc)) from None
        with self.edit("fiducial added") as plan:
            if plan.fiducials_locked:
                raise Refused("fiducials are locked; unlock them first")
            radii = [f.radius_mm for f in plan.fiducials]
            if radius_mm is not None:
                r, why = plan_checks.real_number(radius_mm, "fiducial radius")
                if why:
                    raise Refused(why)
            else:
                r = float(np.median(radii)) if radii else 4.0
            lo, hi = plan_checks.LIMITS.radius_mm
            if not (lo <= r <= hi):
                raise Refused(f"fiducial radius must be between {lo:g} and {hi:g} mm, not {r:g}")
            for f in plan.fiducials:
                if f.status != "rejected" and np.linalg.norm(f.centre_lps_mm - p) < 2 * r:
                    raise Refused(f"too close to fiducial {f.id} ({np.linalg.norm(f.centre_lps_mm - p):.1f} mm)")
            verified, how = plan_checks.check_added_fiducial(self._anatomy(), p, r)
            if verified is False and not manual:
                raise Refused(f"{how}; pick the ball's centre, or add it as manual (unverified)")
            fid = max((f.id for f in plan.fiducials), default=-1) + 1
            plan.fiducials.append(PlanFiducial(fid, p, r, 1.0, "added", bool(verified)))
        self._bus.event("fiducial_added", f"fiducial {fid} added by the operator", {"id": fid, "centre_lps_mm": p.tolist(),
                                                                                    "radius_mm": r, "verified": verified,
                                                                                    "check": how})
        if not verified:
            self._bus.alert("warning", "fiducial_unverified", f"fiducial {fid} added manual, unverified: {how}",
                            {"id": fid})
            return CommandResult.done(f"fiducial {fid} added (manual, unverified: {how})")
        return CommandResult.done(f"fiducial {fid} added")

    @command
    def confirm_fiducials(self) -> CommandResult:
        """Lock the fiducial set: needs >= ``config.min_fiducials`` confirmed or added fiducials,
        each passing its check, no two overlapping. Refused (nothing changes) when the plan cannot be saved."""
        with self._lock:
            if self.store.plan.fiducials_locked:
                return CommandResult.done("fiducials already locked")
            n = len(self.store.plan.usable_fiducials())
            need = self._config.min_fiducials
            if n < need:
                raise Refused(f"{n} fiducials confirmed; at least {need} are needed")
            with self.edit("fiducials locked") as plan:
                plan.fiducials_locked = True
                for f in plan.usable_fiducials():
                    why = plan_checks.check_fiducial(f.id, f.centre_lps_mm, f.radius_mm, f.score, f.status)
                    if why:
                        raise Refused(why)
                why = plan_checks.check_fiducial_set(plan.fiducials) or plan_checks.check_locked(plan, need)
                if why:
                    raise Refused(why)
                ids = [f.id for f in plan.usable_fiducials()]
        self._bus.event("fiducials_locked", f"fiducial set locked ({n} fiducials: {ids})", {"ids": ids})
        return CommandResult.done(f"{n} fiducials locked")

    @command
    def set_fiducial_role(self, fid_id: int, role: str) -> CommandResult:
        """Give fiducial ``fid_id`` the role ``"registration"`` (used in the fit, the default) or
        ``"validation"`` (seen by the camera but kept out of the fit, to verify it: see
        ``engine/verification.py``). At least ``config.min_fiducials`` usable fiducials must keep the
        registration role. Refused while the fiducials are locked, or when the plan cannot be saved."""
        why = plan_checks.check_role(fid_id, role)
        if why:
            raise Refused(why)
        with self.edit("fiducial role") as plan:
            if plan.fiducials_locked:
                raise Refused("fiducials are locked; unlock them first")
            f = plan.fiducial(int(fid_id))
            if f is None:
                raise Refused(f"no fiducial with id {fid_id}")
            old, f.role = f.role, role
            left = len(plan.registration_fiducials())
            if role == "validation" and left < self._config.min_fiducials:
                usable = {id(x) for x in plan.usable_fiducials()}
                pending = sum(1 for x in plan.fiducials if id(x) not in usable and x.status == "detected")
                hint = (f"; {pending} more {'is' if pending == 1 else 'are'} not confirmed yet: confirm the "
                        f"fiducials first, then choose the validation ones") if pending else ""
                raise Refused(f"only {left} fiducial{'' if left == 1 else 's'} would remain for the registration; "
                              f"at least {self._config.min_fiducials} are needed{hint}")
        self._bus.event("fiducial_role", f"fiducial {fid_id}: {role} (was {old})",
                        {"id": int(fid_id), "role": role, "previous": old})
        return CommandResult.done(f"fiducial {fid_id}: {role}")

    @command
    def set_ball_finish(self, finish: str | None) -> CommandResult:
        """State the finish of this patient's kit's balls in the plan: "matte", "glossy", "read"
        (each frame's highlight decides) or None (the session's launch setting,
        ``SessionConfig.ball_finish``). A glossy kit beside its contact shadows needs more balls in
        view before a pose is trusted (vision's ``TrackerConfig.ball_finish``); a camera applies
        the plan's finish when it starts, so a running one is restarted with it (its pose goes:
        it was judged by the old rules). Refused: a bad word, the robot armed or tracking (the
        finish changes which poses are trusted), or the plan cannot be saved."""
        if finish is not None:
            why = plan_checks.check_ball_finish(finish)
            if why:
                raise Refused(why)
        state = self._robot_state()
        if state not in ("disarmed", "estopped"):
            raise Refused(f"the robot is {state}: disarm it before changing the balls' finish "
                          "(it changes which poses are trusted)")
        with self.edit("ball finish") as plan:
            old, plan.ball_finish = plan.ball_finish, finish
        said = "the session's setting" if finish is None else finish
        self._bus.event("ball_finish_set", f"balls' finish: {said} (was "
                        f"{'the session setting' if old is None else old})", {"finish": finish, "previous": old})
        if old != finish:
            self._plan_changed(f"balls' finish changed to {said}", True)
        return CommandResult.done(f"balls' finish: {said}")

    @command
    def unlock_fiducials(self) -> CommandResult:
        """Back to editing the fiducials (refused while armed or tracking, or when the plan cannot be saved)."""
        if self._robot_state() not in ("disarmed", "estopped"):
            raise Refused("disarm the robot before editing fiducials")
        with self._lock:
            if not self.store.plan.fiducials_locked:
                return CommandResult.done("fiducials not locked")
            with self.edit("fiducials unlocked") as plan:
                plan.fiducials_locked = False
        self._bus.event("fiducials_unlocked", "fiducial set unlocked for editing")
        self._plan_changed("fiducials unlocked for editing", False)
        return CommandResult.done("fiducials unlocked")

    # ================================================================== path planning
    def set_entry(self, p_lps_mm) -> CommandResult:
        """Set the needle's entry point: ``p_lps_mm`` (3,) CT LPS mm, finite. Refused while the
        robot is armed, tracking or holding (:data:`ENGAGED_REFUSAL`), before the fiducials are locked, and when the path fails :func:`plan_checks.check_path`
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

    @command
    def _set_path_point(self, which: str, p_lps_mm) -> CommandResult:
        try:
            p = _point3(p_lps_mm)
        except InputError as exc:
            raise Refused(str(exc)) from None
        if self._robot_state() in ENGAGED:
            raise Refused(ENGAGED_REFUSAL)
        with self.edit(f"{which} set") as plan:
            if not plan.fiducials_locked:
                raise Refused("confirm the fiducials before planning the path")
            old = getattr(plan, f"{which}_lps_mm")
            setattr(plan, f"{which}_lps_mm", p)
            why = self._point_problem(which, p, plan)
            if why:
                raise Refused(why)
        self._bus.event(f"{which}_set", f"{which} set to ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm LPS",
                        {"lps_mm": p.tolist(), "previous": None if old is None else old.tolist()})
        if old is None or not np.array_equal(old, p):
            self._plan_changed(f"{which} changed", True)
        return CommandResult.done(f"{which} set")

    def _point_problem(self, which: str, p: np.ndarray, plan: Plan) -> str | None:
        """The checks of one path point (caller holds the lock): its own anatomy check, and the
        whole path's checks once both points are set."""
        a = self._anatomy()
        if a is not None:
            why = (plan_checks.check_entry_anatomy(p, a) if which == "entry" else plan_checks.check_target_anatomy(p, a))
            if why:
                return why
        if plan.path_complete:
            return plan_checks.check_path(plan.entry_lps_mm, plan.target_lps_mm, plan.fiducials, a)
        return None

    @command
    def set_hand_eye(self, T_base_cam_mm) -> CommandResult:
        """Set the hand-eye transform and save it in the plan.

        ``T_base_cam_mm``: 4x4 ``T_base_cam`` (camera frame -> robot base frame), translation in mm.
        Refused (one line, nothing changes) unless :func:`plan_checks.check_hand_eye` passes (finite,
        orthonormal rotation with det +1, last row 0 0 0 1, camera within 3 m of the base), while
        the robot is armed, tracking or holding (:data:`ENGAGED_REFUSAL`), or when the plan cannot be saved."""
        why = plan_checks.check_hand_eye(T_base_cam_mm)
        if why:
            raise Refused(why)
        T = np.asarray(T_base_cam_mm, dtype=float)
        if self._robot_state() in ENGAGED:
            raise Refused(ENGAGED_REFUSAL)
        with self.edit("hand-eye") as plan:
            plan.T_base_cam = T.copy()
        self._bus.event("hand_eye_set", "hand-eye calibration T_base_cam set", {"T_base_cam_mm": T.tolist()})
        return CommandResult.done("hand-eye set")

    def store_camera(self, source: str, calibration_path, K, dist, image_size) -> str | None:
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
            p = self.store.plan
            recorded = p.integrity.get("calibration_sha256")
            changed = (calibration_path and p.calibration_path == calibration_path and recorded
                       and cal_sha != recorded)
            same = (p.camera_source == source and p.calibration_path == calibration_path and p.K is not None
                    and K is not None and np.array_equal(p.K, K) and not changed)
            if same:
                return None
            try:
                with self.edit("camera calibration") as plan:
                    plan.camera_source, plan.calibration_path = source, calibration_path
                    plan.K = None if K is None else np.asarray(K, float).copy()
                    plan.dist = None if dist is None else np.asarray(dist, float).ravel().copy()
                    plan.image_size = size
                    if cal_sha:
                        plan.integrity["calibration_sha256"] = cal_sha
                    else:
                        plan.integrity.pop("calibration_sha256", None)
            except Refused as exc:
                return str(exc)
        if changed:
            self.need_reconfirm("calibration_changed", f"the calibration file {calibration_path} changed since "
                                "the plan recorded it (content hash differs)", {"path": calibration_path})
        self._bus.event("camera_calibration", f"camera {source}: calibration stored in the plan",
                        {"source": source, "calibration_path": calibration_path,
                         "K": None if K is None else np.asarray(K).tolist(),
                         "dist": None if dist is None else np.asarray(dist).ravel().tolist(),
                         "image_size": None if image_size is None else list(image_size)})
        return None
