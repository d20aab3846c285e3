"""Alarms that cannot hide: the session's list of *active conditions*, most important first.

``snap.alerts`` is history (what happened, newest last); an alert scrolls away when the next
one comes. ``snap.alarms`` is the present: every condition that holds *now* (e-stop latched, arm
lost, pose not trusted, fiducials occluded, camera frozen, PIN locked, ...), each with the time
it began and how many episodes it had, until the condition clears. A new, less important
condition never replaces a more important one on screen.

The :class:`AlarmBoard` is bookkeeping only (no threads; the engine's parts call :meth:`set`
when a condition holds and :meth:`clear` when it is over, as often as they like):

* one *episode* per start: ``set`` on an active code refreshes its message, nothing else;
* ``linger_s`` (per code): the shortest time a condition stays shown after it was last set, so a
  one-tick glitch is readable and a condition re-set within that time stays one episode (this is
  display hysteresis; the engine's decisions never wait on it);
* the *dwell* of a condition that may flap (``raise_after_s`` / ``clear_after_s``, per code): it
  becomes an episode (shown, counted, reported) only once it has stood for ``raise_after_s``
  since it was first set, short gaps included, and the episode ends only once it has been
  absent (cleared and not set again) for ``clear_after_s``. A condition set again within
  ``clear_after_s`` of its clear is the same episode, so a condition toggling every 100 ms is one
  alarm, not one per toggle; one that ends before ``raise_after_s`` was never an episode (the
  snapshot's pose and robot state still say what happened). Like ``linger_s`` this is only what
  is *shown and reported*: the arm's hold is the caller's, immediate, and never waits on it;
* ``set`` returns True when the caller should write an alert (audit row): every new episode of
  a safety condition, but for *technical* conditions (stale pose, control-loop overrun, ...) at
  most one per ``quiet_s`` (10 s); the episodes in between are counted (``Alarm.count``) and the
  next report says how many went unreported (:meth:`unreported`).

Codes, levels, priorities and every flag are rows of :data:`CATALOGUE` (0 = most important):
adding a condition is adding a row. ``set`` may raise the level for one episode (a pose
condition is an ``"alarm"`` while the arm follows the head, a ``"warning"`` otherwise). Times are
session-clock seconds.

Alert codes (``Event.kind == "alert"``; level in brackets; for a catalogued code its row's) the UI
can rely on:
``occlusion`` [warning] fewer than ``min_fiducials`` matched, arm holds; ``pose_jump`` [warning] the
pose disagrees with the last trusted one (a wrong pose or a real jump; followed after
``confirm_frames`` consistent frames), arm holds; ``bad_pose`` [warning] FRE too large; ``pose_lost``
[warning] the estimator failed; ``pose_stale`` [warning] freshest trusted pose older than
``max_pose_age_s``; ``pipeline_overloaded`` [warning] the same, because this computer cannot
estimate the frames in time (frames dropped, each estimate longer than a frame period:
engine/loop/load.py), not a camera fault; ``camera_freeze`` [alarm] the camera repeats its frames bit for bit (a frozen
driver); ``camera_late`` [warning] frames still arrive, new ones, but none for ``freeze_after_s``
(a busy machine or a slow pipeline: the arm holds until fresh poses return, as the robot's own
0.1 s freshness rule makes it); ``camera_stalled`` [alarm] no new frame at all for
``stall_after_s`` (a camera that stopped delivering or was unplugged); ``resumed`` [info]
the pose is trusted again (tracking resumes by itself); ``fiducials_lost`` / ``fiducials_back``
[info] fiducials left / re-entered the camera's view (with how many remain);
``fiducials_set_aside`` [info] a fiducial found but left out of the pose because the other balls
put it more than a pixel or two away (partly hidden, a reflection; the pose comes from the
others: vision's ``disagreement_quantile``); ``fiducial_set_aside_long`` [warning] a ball set aside
in at least 60 % of the estimates of the last 3 s (``SET_ASIDE_WINDOW_S``, ``SET_ASIDE_SHARE``:
check it; the arm does not hold for it; shown until that has not held for 5 s); ``camera_stopped``
[warning]; ``engine_error`` [alarm] an internal error in the engine loop (arm held);
``robot_disconnected`` [alarm] /
``robot_connected`` [info]; real cameras: ``camera_ended`` [warning] the video/folder ended,
``frame_unreadable`` [warning] a corrupt frame (skipped), ``camera_disconnected`` [alarm],
``camera_uncalibrated`` / ``camera_compressed`` / ``camera_short_lens`` / ``colour_clash``
[warning] nominal intrinsics / lossy frames (MJPEG, JPEG files, a lossy video codec) / a lens
that images the balls under 10 px from the layout planner's closest distance, outside the range
trust was judged on (vision/lens_range.py) / a large area of the balls' colour (learn the
colour), shown while that camera runs (the last while the area is seen),
``frame_size`` [alarm] frame size differs from the calibration, ``frame_grayscale`` [alarm] the
frames are grayscale (a monochrome camera or grayscale files: no ball can be found), ``camera_moved``
[alarm] the camera moved after the hand-eye (vision's CameraMotionMonitor); poses: ``tre_limit``
[warning] predicted error at the target over ``max_predicted_tre_mm``, ``weak_geometry`` /
``pose_implausible`` [warning], ``fiducial_moved`` [warning] a ball moved since the CT (named,
with its shift in mm; excluded from then on); ``robot_warning`` [warning] from the robot's safety layer; integrity
(engine/plan/editor.py, engine/audit.py): ``plan_field_rejected`` / ``plan_changed_outside`` /
``plan_reconfirm_pending`` / ``plan_ct_changed`` / ``plan_ct_missing`` / ``calibration_changed`` /
``plan_path_invalid`` / ``home_unwritable`` / ``audit_unavailable`` / ``audit_delayed`` / ``audit_lost``
[alarm], ``home_writable`` / ``audit_recovered`` [info], ``fiducial_unverified`` [warning]; ``estop``
[alarm]; ``estop_unconfirmed`` [alarm] STOP signalled but the robot controller did not confirm it;
``plan_changed_armed`` [alarm] a plan revision reached an armed, tracking or holding robot, which
was disarmed first (stands until the robot is armed again);
``session_unlocked`` [warning] the session folder could not be locked (read-only); ``pin_lockout`` [alarm] too many wrong PIN tries, arming and taking control locked (each
wrong try is an ``arm_refused`` / ``control_refused`` *event*, never an alert, never the PIN); ``camera_failed`` / ``ct_failed`` / ``plan_save_failed``
/ ``plan_unreadable`` [alarm] (the last stands until a new plan is saved); ``fiducials_detection`` / ``head_sphere`` [warning]. Decisions and
state changes are ``kind == "event"`` (``fiducial_confirmed``, ``fiducials_locked``, ``entry_set``,
``arm``, ``tracking_started``, ``robot_state`` (one per robot transition, in order, with its own
reason), ``session_lock_recovered`` (this session took over the folder lock of a process that was
killed), ``fault_injected``, ...); all of them are in the audit log.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from monotracker.engine.snapshot import Alarm

log = logging.getLogger(__name__)
_UNLISTED_SEEN: set[str] = set()


@dataclass(frozen=True)
class AlarmKind:
    """One row of the catalogue: everything the engine decides about a condition, in one place.

    ``level``: ``"alarm" | "warning" | "info"``, of its board entry and of every alert raised with
    its code (the event bus takes it from here). ``priority``: 0 = most important.
    ``technical``: reports (alerts) rate-limited to one per ``quiet_s``. ``linger_s``: shown at
    least this long after it was last set. ``holds_arm``: a pose condition: the arm holds while it
    stands, one at a time, raised to ``"alarm"`` while the arm follows the head.
    ``freshness``: the pose stream stopped being fresh; resuming from it waits ``resume_dwell_s``.
    ``camera_setup``: a condition of the running camera's setup, raised by its rig as it starts
    and shown while that camera runs. ``pulse``: shown for its linger time from each report (it
    has no end of its own). ``derived``: the session derives it from its state at every snapshot.
    ``verdict``: the trust verdict's code for it where that differs (``GateVerdict.code``).
    ``raise_after_s`` / ``clear_after_s``: the dwell of a condition that may flap (see the module
    docstring): an episode only once it stood this long, over only once absent this long (s).
    ``remedy``: what the team can do about it, one line ("" where the message says it).
    """

    level: str
    priority: int
    technical: bool = False
    linger_s: float = 1.0
    holds_arm: bool = False
    freshness: bool = False
    camera_setup: bool = False
    pulse: bool = False
    derived: bool = False
    verdict: str = ""
    raise_after_s: float = 0.0
    clear_after_s: float = 0.0
    remedy: str = ""


_HOLD = {"holds_arm": True}
#: too few balls found for a pose: what the team can change (issue 28: gloves, instruments and
#: drapes take most of the balls lost on realistic frames)
_R_FEW = ("uncover the balls (hands, instruments, drapes) so that at least 4 are in the camera's view; more balls or "
          "a nearer camera help")
#: a ball set aside by the estimator (vision's ``disagreement_quantile``) is a condition while it
#: was set aside in at least SET_ASIDE_SHARE of the estimates of the last SET_ASIDE_WINDOW_S (s;
#: a single frame is only the info alert ``fiducials_set_aside``); shown until that has not held
#: for SET_ASIDE_CLEAR_S (s)
SET_ASIDE_WINDOW_S = 3.0
SET_ASIDE_SHARE = 0.6
SET_ASIDE_CLEAR_S = 5.0
_R_ASIDE = ("check that the ball is firmly attached, clean and not partly covered (drape, glove, instrument); "
            "if it moved on the skin, re-register")
#: the dwell of the freshness conditions that flap on a busy machine (s): raised once they stood
#: 0.5 s (a single late frame is no alarm, a busy spell is), ended once absent for 60 s (a spell
#: that comes back within a minute is the same episode: at most one episode a minute)
_FLAP_RAISE_S = 0.5
_FLAP_CLEAR_S = 60.0
#: every code that reaches the board (``tests/engine/test_alarm_catalogue.py`` fails on a code
#: without a row). A code the board does not know is shown as an alarm right under the e-stop and
#: logged as an error: never hidden, never rate-limited.
CATALOGUE: dict[str, AlarmKind] = {
    # safety: the arm and what it follows
    "estop": AlarmKind("alarm", 0, linger_s=0.0),
    # STOP signalled but the robot's controller did not confirm it: use the robot's own e-stop
    "estop_unconfirmed": AlarmKind("alarm", 0, linger_s=0.0),
    "robot_disconnected": AlarmKind("alarm", 1, linger_s=0.0),
    "engine_error": AlarmKind("alarm", 2, linger_s=2.0, **_HOLD),
    "pose_lost": AlarmKind("warning", 3, verdict="estimator", remedy=_R_FEW, **_HOLD),  # the estimator failed
    "bad_pose": AlarmKind("warning", 3, verdict="fre", remedy="check that no ball moved since the CT and that nothing "
                          "of the balls' colour lies near them", **_HOLD),  # FRE too large
    "pose_jump": AlarmKind("warning", 3, verdict="jump", remedy="if the head did not move, check that every ball is "
                           "firmly attached", **_HOLD),  # pose disagrees with the last trusted one
    "occlusion": AlarmKind("warning", 4, remedy=_R_FEW, **_HOLD),
    # bit-identical frames: a frozen driver, at once (tests/engine/test_frozen_camera.py)
    "camera_freeze": AlarmKind("alarm", 5, freshness=True, **_HOLD),
    # no new frame at all for stall_after_s: the camera stopped delivering
    "camera_stalled": AlarmKind("alarm", 5, freshness=True, **_HOLD),
    "camera_failed": AlarmKind("alarm", 5, linger_s=0.0),
    "camera_stopped": AlarmKind("warning", 6, linger_s=0.0, **_HOLD),
    "camera_disconnected": AlarmKind("alarm", 5, linger_s=0.0, **_HOLD),
    "camera_ended": AlarmKind("warning", 6, linger_s=0.0, **_HOLD),
    "frame_size": AlarmKind("alarm", 5, linger_s=0.0, **_HOLD),  # frames do not match the calibration
    "frame_grayscale": AlarmKind("alarm", 5, linger_s=0.0, **_HOLD),  # a monochrome camera or grayscale files
    "camera_moved": AlarmKind("alarm", 5, linger_s=0.0, **_HOLD),  # the camera moved after the hand-eye
    "frame_unreadable": AlarmKind("warning", 6, **_HOLD),
    "tre_limit": AlarmKind("warning", 3, remedy="uncover more balls or bring the camera nearer (the Plan step's layout "
                           "says what this camera needs; with glossy balls beside their shadows, 7 or more in view); "
                           "the estimate tightens over the next frames", **_HOLD),  # predicted error at the target over the limit
    "weak_geometry": AlarmKind("warning", 3, remedy="the balls found lie nearly on a line or a plane: uncover the "
                               "others", **_HOLD),
    "pose_implausible": AlarmKind("warning", 3, **_HOLD),
    "fiducial_moved": AlarmKind("warning", 3, linger_s=0.0),
    # the same ball left out of the pose in most frames of the last SET_ASIDE_WINDOW_S (the others
    # put it a pixel or two away); over once that stopped for SET_ASIDE_CLEAR_S; the arm does not
    # hold for it (the pose from the others is judged like any other)
    "fiducial_set_aside_long": AlarmKind("warning", 6, clear_after_s=SET_ASIDE_CLEAR_S, remedy=_R_ASIDE),
    # freshness on a busy machine (issue 33): the arm holds at once, the board shows one episode
    # per busy spell (shown once it stood 0.5 s, flaps included; over after 60 s without)
    "camera_late": AlarmKind("warning", 7, technical=True, freshness=True, raise_after_s=_FLAP_RAISE_S,
                             clear_after_s=_FLAP_CLEAR_S, **_HOLD),
    "pose_stale": AlarmKind("warning", 7, technical=True, freshness=True, raise_after_s=_FLAP_RAISE_S,
                            clear_after_s=_FLAP_CLEAR_S, **_HOLD),
    # this computer cannot estimate the camera's frames in time (engine/loop/load.py): frames
    # dropped, poses late; not a camera fault (the arm holds at once; one episode per busy spell)
    "pipeline_overloaded": AlarmKind("warning", 7, technical=True, freshness=True, raise_after_s=_FLAP_RAISE_S,
                                     clear_after_s=_FLAP_CLEAR_S, **_HOLD),
    "plan_save_failed": AlarmKind("alarm", 8, linger_s=0.0),
    # a plan revision reached an armed / tracking / holding robot: it was disarmed (arming is for one plan)
    "plan_changed_armed": AlarmKind("alarm", 8, linger_s=0.0),
    "pin_lockout": AlarmKind("alarm", 9, linger_s=0.0),
    "login_lockout": AlarmKind("alarm", 9, linger_s=0.0),  # the web login (--allow-remote) refused wrong passwords
    # the saved session: nothing reported as done that is not on disk, edits outside the app
    "home_unwritable": AlarmKind("alarm", 8, linger_s=0.0, derived=True),
    "audit_unavailable": AlarmKind("alarm", 10, linger_s=0.0),
    "audit_delayed": AlarmKind("alarm", 11, linger_s=0.0, derived=True),
    "audit_lost": AlarmKind("alarm", 10, linger_s=0.0, derived=True),
    # the log no longer matches its anchor (engine/audit.py)
    "audit_tampered": AlarmKind("alarm", 10, linger_s=0.0, derived=True),
    # no MAC / anchor (engine/integrity.py)
    "integrity_key_unavailable": AlarmKind("warning", 11, linger_s=0.0, derived=True),
    "plan_ct_missing": AlarmKind("alarm", 12, linger_s=0.0, derived=True),
    "plan_ct_changed": AlarmKind("alarm", 12, linger_s=0.0),
    "calibration_changed": AlarmKind("alarm", 12, linger_s=0.0),
    "plan_changed_outside": AlarmKind("alarm", 12, linger_s=0.0),
    "plan_reconfirm_pending": AlarmKind("alarm", 12, linger_s=0.0, derived=True),
    "plan_field_rejected": AlarmKind("alarm", 13, linger_s=0.0),
    "session_unlocked": AlarmKind("warning", 14, linger_s=0.0),  # the session folder could not be locked
    # technical
    "loop_overrun": AlarmKind("warning", 20, technical=True, linger_s=10.0, pulse=True),
    "robot_warning": AlarmKind("warning", 21, technical=True, linger_s=10.0, pulse=True),
    "camera_uncalibrated": AlarmKind("warning", 22, linger_s=0.0, camera_setup=True),
    "camera_compressed": AlarmKind("warning", 22, linger_s=0.0, camera_setup=True),  # frames through JPEG/lossy video
    # a lens that images the balls under the judged size (vision/lens_range.py)
    "camera_short_lens": AlarmKind("warning", 22, linger_s=0.0, camera_setup=True),
    "colour_clash": AlarmKind("warning", 22, linger_s=0.0, camera_setup=True,
                              remedy="click a ball in the camera view to learn its colour, or cover that area"),  # a drape of the balls' hue
    "plan_unreadable": AlarmKind("alarm", 23, linger_s=0.0),
    "ct_failed": AlarmKind("alarm", 24, linger_s=0.0),
    "acquiring": AlarmKind("info", 30, technical=True, **_HOLD),
}
_UNKNOWN = AlarmKind("alarm", 1, linger_s=0.0)


def _codes(flag: str) -> tuple[str, ...]:
    return tuple(code for code, kind in CATALOGUE.items() if getattr(kind, flag))


#: the conditions under which the arm holds for the pose (one at a time)
POSE_CODES = _codes("holds_arm")
#: holds about a pose stream that stopped being fresh; resuming from them needs resume_dwell_s
FRESHNESS_CODES = _codes("freshness")
#: conditions of the running camera's setup: raised by its rig as it starts, shown while it runs
CAMERA_SETUP_CODES = _codes("camera_setup")
#: conditions the session derives from its state (folder writable, re-confirmation, CT, audit)
DERIVED_CODES = _codes("derived")
#: the trust verdict's code -> the condition's code
VERDICT_CODES = {kind.verdict: code for code, kind in CATALOGUE.items() if kind.verdict}


def level_of(code: str, level: str) -> str:
    """The level an alert with ``code`` carries: its catalogue row's, else ``level`` (alerts that
    are history only: ``resumed``, ``fiducials_lost``, ...)."""
    kind = CATALOGUE.get(code)
    return level if kind is None else kind.level


LEVEL_RANK = {"alarm": 0, "warning": 1, "info": 2}


@dataclass
class _State:
    level: str
    message: str
    since: float
    last_set: float
    clear_asked: bool = False
    data: dict | None = None
    raised: bool = True  # False: inside its raise dwell (not shown, counted or reported yet)
    cleared_at: float | None = None  # the clear that began the current absence (s)


def _over(st: _State, k: AlarmKind, now: float) -> bool:
    """The condition has been absent long enough to leave the board (linger and clear dwell)."""
    return (st.clear_asked and now - st.last_set >= k.linger_s
            and (st.cleared_at is None or now - st.cleared_at >= k.clear_after_s))


class AlarmBoard:
    """The active conditions of one session (thread-safe). ``quiet_s``: shortest time between two
    reports (alerts) of the same technical condition."""

    def __init__(self, quiet_s: float = 10.0):
        self.quiet_s = float(quiet_s)
        self._lock = threading.Lock()
        self._active: dict[str, _State] = {}
        self._episodes: dict[str, int] = {}
        self._last_report: dict[str, float] = {}
        self._held_back: dict[str, int] = {}  # episodes not reported since the last report
        self._unreported: dict[str, int] = {}  # episodes held back before the latest report

    @staticmethod
    def kind(code: str) -> AlarmKind:
        kind = CATALOGUE.get(code)
        if kind is None:
            if code not in _UNLISTED_SEEN:
                _UNLISTED_SEEN.add(code)
                log.error("alarm code %r has no row in alarms.CATALOGUE: shown as an alarm", code)
            return _UNKNOWN
        return kind

    def set(self, code: str, message: str, now: float, level: str | None = None) -> bool:
        """The condition ``code`` holds at ``now`` (s); ``message`` one line. Returns True when
        the caller should report it (write an alert): a new episode, rate-limited if technical."""
        k = self.kind(code)
        lvl = level or k.level
        now = float(now)
        with self._lock:
            st = self._active.get(code)
            if st is not None and st.clear_asked and _over(st, k, now):
                del self._active[code]  # absent long enough: this is a new episode
                st = None
            if st is not None:
                st.message, st.last_set, st.clear_asked, st.cleared_at = message, now, False, None
                if LEVEL_RANK.get(lvl, 1) < LEVEL_RANK.get(st.level, 1):
                    st.level = lvl  # worsened within the episode (e.g. tracking started)
                if not st.raised and now - st.since >= k.raise_after_s:
                    return self._raise(code, k, st, now)  # it stood its raise dwell (gaps included)
                return False
            st = self._active[code] = _State(lvl, message, now, now, raised=k.raise_after_s <= 0)
            return self._raise(code, k, st, now) if st.raised else False

    def _raise(self, code: str, k: AlarmKind, st: _State, now: float) -> bool:
        """A new episode of ``code`` (lock held): count it; True when it is to be reported."""
        st.raised = True
        self._episodes[code] = self._episodes.get(code, 0) + 1
        if k.technical and now - self._last_report.get(code, -float("inf")) < self.quiet_s:
            self._held_back[code] = self._held_back.get(code, 0) + 1
            return False
        self._last_report[code] = now
        self._unreported[code] = self._held_back.pop(code, 0)
        return True

    def pending(self, code: str) -> bool:
        """``code`` was set and is inside its raise dwell (not an episode yet)."""
        with self._lock:
            st = self._active.get(code)
            return st is not None and not st.raised

    def unreported(self, code: str) -> int:
        """Episodes of ``code`` held back before its latest report (for that report's message;
        read once: the count is forgotten)."""
        with self._lock:
            return self._unreported.pop(code, 0)

    def clear(self, code: str, now: float) -> bool:
        """The condition is over at ``now``; it leaves the list once shown for ``linger_s`` and,
        with a clear dwell, once absent for ``clear_after_s`` (set again before that: the same
        episode). Returns True if it was active (an episode, not a condition inside its raise
        dwell)."""
        now = float(now)
        with self._lock:
            st = self._active.get(code)
            if st is None:
                return False
            k = self.kind(code)
            if not st.clear_asked:
                st.clear_asked, st.cleared_at = True, now
            if _over(st, k, now) or (not st.raised and k.clear_after_s <= 0):
                del self._active[code]
            return st.raised

    def clear_all(self, codes, now: float, keep: str | None = None) -> None:
        """``clear`` every code in ``codes`` except ``keep``."""
        for c in codes:
            if c != keep:
                self.clear(c, now)

    def is_active(self, code: str) -> bool:
        """``code`` is an episode on the board (shown), lingering or dwelling included."""
        with self._lock:
            st = self._active.get(code)
            return st is not None and st.raised

    def episodes(self, code: str) -> int:
        """How many times ``code`` began since the session started."""
        with self._lock:
            return self._episodes.get(code, 0)

    def active(self, now: float) -> tuple[Alarm, ...]:
        """The active conditions at ``now``, most important first (priority, then level, then the
        oldest first)."""
        now = float(now)
        with self._lock:
            for code in [c for c, st in self._active.items() if _over(st, self.kind(c), now)]:
                del self._active[code]
            items = [Alarm(code, st.level, self.kind(code).priority, self._shown(code, st, now), st.since,
                           self._episodes[code], self.kind(code).remedy)
                     for code, st in self._active.items() if st.raised]
        items.sort(key=lambda a: (a.priority, LEVEL_RANK.get(a.level, 1), a.since, a.code))
        return tuple(items)


    def _shown(self, code: str, st: _State, now: float) -> str:
        """The message shown: a condition kept by its clear dwell says how long it has been away."""
        if st.clear_asked and st.cleared_at is not None and self.kind(code).clear_after_s > 0:
            return f"{st.message} (last {now - st.cleared_at:.0f} s ago)"
        return st.message


class Alarms:
    """The session's alarms: the :class:`AlarmBoard` of active conditions and the alerts that
    report them (on the event bus ``events``), on the session ``clock`` (s). Thread-safe.

    :meth:`alert` is how every part raises an alert: a ``pulse`` row (robot warnings; a control
    loop overrun is shown as ``loop_overrun``) is also shown on the board for its linger time and
    reported at most once per quiet time; a ``camera_setup`` row is also an active condition
    until :meth:`clear`."""

    def __init__(self, events, clock, quiet_s: float = 10.0):
        self.board = AlarmBoard(quiet_s)
        self._bus = events
        self._clock = clock

    def now(self) -> float:
        return float(self._clock())

    def alert(self, level: str, code: str, message: str, data: dict | None = None):
        """Raise an alert (to subscribers and the audit log); returns the event, or None when a
        repeated pulse was held back. ``level`` counts only for a code without a row."""
        on_board = "loop_overrun" if code == "robot_warning" and "overran" in message else code
        kind = CATALOGUE.get(on_board)
        if kind is not None and kind.pulse:
            now = self.now()
            report = self.board.set(on_board, message, now)
            self.board.clear(on_board, now)  # a pulse: shown for its linger time
            if not report:
                log.info("%s (not re-reported): %s", code, message)
                return None
        elif kind is not None and kind.camera_setup:
            self.board.set(code, message, self.now())
        return self._bus.alert(level, code, message, data)

    def persistent(self, code: str, message: str, data: dict | None = None):
        """An alert that is also an active condition (``snap.alarms``) until it is cleared."""
        self.board.set(code, message, self.now())
        return self._bus.alert(level_of(code, "alarm"), code, message, data)

    def clear(self, code: str) -> None:
        """Condition ``code`` no longer holds."""
        self.board.clear(code, self.now())

    def clear_all(self, codes, keep: str | None = None) -> None:
        self.board.clear_all(codes, self.now(), keep=keep)

    def active(self, derived: dict[str, str]) -> tuple[Alarm, ...]:
        """The active conditions now, most important first; ``derived``: the ``derived`` rows that
        stand now (code -> one line), set on the board, the others cleared."""
        now = self.now()
        for code in DERIVED_CODES:
            if code in derived:
                self.board.set(code, derived[code], now)
            else:
                self.board.clear(code, now)
        return self.board.active(now)
