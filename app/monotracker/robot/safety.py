"""Safety layer: always on, independent of the controller (it never calls APFF code).

State machine (every transition is logged with a timestamp and reason, and reported through
the ``on_transition`` callback)::

    disarmed --arm (operator)--> armed --start_tracking (operator)--> tracking
    tracking --stop_tracking--> armed           tracking --fault--> holding
    holding --start_tracking (operator)--> tracking
    holding --fresh target after a stale/invalid spell (auto_resume)--> tracking
    any --estop / arm lost / exception--> estopped (latched) --reset (operator)--> disarmed
    armed/holding/tracking --disarm--> disarmed

Only ``tracking`` lets controller commands through, and then only after :meth:`filter_command`
has limited them: joint speed, joint acceleration (relative to the last command), braking
before joint position limits, tool (needle tip) linear and angular speed, and the keep-out
sphere around the head (motion that takes a needle point deeper into the head sphere outside the
planned-path corridor is cut). In every other state the arm is stopped (``stop`` with the
configured deceleration).

Target checks (:meth:`check_target`): a pose flagged invalid by the pose stream, or no fresh
target, puts ``tracking`` into ``holding``; tracking resumes by itself when fresh valid poses
return close to the last accepted one (``auto_resume``). A NaN / non-rigid pose, a capture stamp
in the future (a clock fault in the pose source) or a jump larger than ``jump_m``/``jump_rad``
also holds, but resuming then needs the operator (``start_tracking`` accepts the newest pose as
the new reference).

Freshness runs on the poses' *capture stamps*, checked every control cycle: the target is fresh
while (a) a pose with a newer capture stamp than the one before arrived within ``stale_s``
(frame gap) and (b) the newest capture is at most ``max_latency_s`` old (pipeline latency budget).
A pose whose stamp is not newer (the same frame re-sent) may update the target but does not
refresh (a); an older stamp (out of order) is ignored. Stale_s alone is not measured from the
capture: the paper's pipeline takes 0.23 s from capture to pose, more than a 0.1 s frame gap.

Units: m, rad, s.
"""

from __future__ import annotations

import enum
import math
import logging
import threading
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from monotracker.geometry import invert_transform
from monotracker.robot.head import Corridor, HeadSphere
from monotracker.robot.kinematics import Kinematics, NeedleTool, joint_limits
from monotracker.robot.lie import adjoint, log3
from monotracker.robot.rigid import rigid_problem

log = logging.getLogger(__name__)


class State(str, enum.Enum):
    DISARMED = "disarmed"
    ARMED = "armed"
    TRACKING = "tracking"
    HOLDING = "holding"
    ESTOPPED = "estopped"


@dataclass(frozen=True)
class Transition:
    """One state change: time ``t`` (s, the safety clock), from/to state, and why. ``seq``: its
    number in this safety layer's history (1, 2, ...; given under the layer's lock, so listeners
    called from different threads can put the transitions back in the order they happened)."""

    t: float
    from_state: State
    to_state: State
    reason: str
    seq: int = 0


@dataclass
class SafetyConfig:
    """Limits (SI). Joint speed 1.0 rad/s and acceleration 3 rad/s^2 are well inside the UR10's
    (2.16-3.2 rad/s) because the tool works next to a head; tool tip 0.15 m/s, 0.6 rad/s."""

    joint_speed: np.ndarray = field(default_factory=lambda: np.full(6, 1.0))
    joint_accel: float = 3.0
    estop_decel: float = 8.0
    position_margin_rad: float = 0.05
    tool_speed_m_s: float = 0.15
    tool_angular_rad_s: float = 0.6
    stale_s: float = 0.1
    max_latency_s: float = 0.5
    #: capture stamps more than this ahead of the safety clock are a clock fault (s)
    future_stamp_s: float = 0.005
    jump_m: float = 0.02
    jump_rad: float = np.radians(10.0)
    auto_resume: bool = True
    keepout_margin_m: float = 0.0
    #: latency allowance added to the braking time when predicting where the needle stops (s)
    keepout_lookahead_s: float = 0.03
    sigma_hold: float = 0.01
    standstill_rad_s: float = 1e-3


@dataclass
class TargetStatus:
    accepted: bool
    reason: str


#: a target's rotation may be off by this much (it went through unit conversions and products)
TARGET_RIGID_TOL = 1e-3


def _rigid_ok(T: np.ndarray) -> bool:
    return rigid_problem(T, TARGET_RIGID_TOL, "target") is None


class SafetyLayer:
    def __init__(self, config: SafetyConfig | None = None, tool: NeedleTool | None = None,
                 corridor: Corridor | None = None,
                 on_transition: Callable[[Transition], None] | None = None):
        self.cfg = config or SafetyConfig()
        self.tool = tool or NeedleTool()
        self.corridor = corridor or Corridor()
        self.on_transition = on_transition
        self.kin = Kinematics()
        self.limits = joint_limits()
        self.state = State.DISARMED
        self.history: list[Transition] = []
        self._lock = threading.RLock()
        self._hold_auto = False
        self.target: np.ndarray | None = None  # last accepted target (m)
        self.target_received = -np.inf
        self.target_stamp = -np.inf
        self.pending: np.ndarray | None = None  # newest rigid target not accepted (jump)
        self.pending_stamp = -np.inf
        self.last_cmd = np.zeros(6)
        self.warnings: list[str] = []
        self._Ad_tip_tool0 = adjoint(invert_transform(self.tool.T_tool0_tip))
        ts = np.linspace(0.0, 1.0, 5)
        self._needle_pts = np.array([[0, 0, self.tool.offset_m + t * self.tool.length_m, 1.0] for t in ts])

    # ------------------------------------------------------------------ state machine
    def _go(self, to: State, reason: str, now: float, auto: bool = False, reset: bool = False) -> Transition | None:
        """Change state (atomically). The e-stop is latched here, at the lowest level: out of
        ``estopped`` only :meth:`reset` may go (``reset=True``), so a transition decided by
        another thread just before an e-stop landed can never overwrite it."""
        with self._lock:
            if to == self.state:
                return None
            if self.state == State.ESTOPPED and not reset:
                return None
            tr = Transition(float(now), self.state, to, reason, len(self.history) + 1)
            self.state = to
            self._hold_auto = auto
            self.history.append(tr)
            log.info("robot safety %s -> %s at %.3f: %s", tr.from_state.value, to.value, now, reason)
        if self.on_transition:
            try:
                self.on_transition(tr)
            except Exception:  # a broken listener must not break safety
                log.exception("transition callback failed")
        return tr

    def arm(self, now: float, connected: bool) -> tuple[bool, str]:
        """Operator action: disarmed -> armed."""
        if self.state == State.ESTOPPED:
            return False, "e-stop is latched: reset first"
        if self.state != State.DISARMED:
            return False, f"cannot arm from {self.state.value}"
        if not connected:
            return False, "arm not connected"
        self._go(State.ARMED, "operator armed", now)
        if self.state != State.ARMED:  # an e-stop landed meanwhile (another thread)
            return False, "e-stop is latched: reset first"
        return True, "armed"

    def disarm(self, now: float, reason: str = "operator disarmed") -> tuple[bool, str]:
        if self.state == State.ESTOPPED:
            return False, "e-stop is latched: reset first"
        self._go(State.DISARMED, reason, now)
        if self.state != State.DISARMED:  # an e-stop landed meanwhile (another thread)
            return False, "e-stop is latched: reset first"
        return True, "disarmed"

    def start_tracking(self, now: float) -> tuple[bool, str]:
        """Operator action: armed/holding -> tracking; needs a fresh valid target. From a
        jump-hold the newest pose becomes the accepted reference (the operator confirms it)."""
        if self.state not in (State.ARMED, State.HOLDING):
            return False, f"cannot start tracking from {self.state.value}" + (
                " (arm first)" if self.state == State.DISARMED else "")
        if (self.pending is not None and now - self.target_received <= self.cfg.stale_s
                and now - self.pending_stamp <= self.cfg.max_latency_s):
            self.target, self.target_stamp, self.pending = self.pending, self.pending_stamp, None
        if not self.target_fresh(now):
            return False, "no fresh valid target pose"
        self._go(State.TRACKING, "operator started tracking", now)
        if self.state != State.TRACKING:  # an e-stop landed meanwhile (another thread)
            return False, "e-stop is latched: reset first"
        return True, "tracking"

    def stop_tracking(self, now: float, reason: str = "operator stopped tracking") -> tuple[bool, str]:
        if self.state not in (State.TRACKING, State.HOLDING):
            return False, f"not tracking ({self.state.value})"
        self._go(State.ARMED, reason, now)
        if self.state != State.ARMED:  # an e-stop landed meanwhile (another thread)
            return False, "e-stop is latched: reset first"
        return True, "armed"

    def hold(self, now: float, reason: str, auto: bool = False) -> None:
        """tracking -> holding. A fault that needs the operator (``auto=False``) arriving during
        a hold that would resume by itself (stale/invalid stream) turns that hold into one that
        needs the operator: a fault's severity must not depend on the stream being stale first."""
        if self.state == State.TRACKING:
            self._go(State.HOLDING, reason, now, auto=auto)
        elif self.state == State.HOLDING and self._hold_auto and not auto:
            with self._lock:
                self._hold_auto = False
            msg = f"holding until the operator resumes: {reason}"
            self.warnings.append(msg)
            log.warning("robot safety at %.3f: %s", now, msg)

    def estop(self, now: float, reason: str) -> None:
        self._go(State.ESTOPPED, reason, now)

    def reset(self, now: float) -> tuple[bool, str]:
        if self.state != State.ESTOPPED:
            return False, f"not e-stopped ({self.state.value})"
        # Start clean: tracking again needs a pose received after the reset (the e-stop may
        # have been a clock or pose-stream fault that makes the old stamps meaningless).
        self.target, self.pending = None, None
        self.target_received = self.target_stamp = self.pending_stamp = -np.inf
        self._go(State.DISARMED, "operator reset the e-stop", now, reset=True)
        return True, "disarmed"

    # ------------------------------------------------------------------ targets
    def check_target(self, T_base_target: np.ndarray, stamp: float, valid: bool, now: float) -> TargetStatus:
        """Validate a new target pose (m). Accepted targets become :attr:`target`."""
        T = np.asarray(T_base_target, dtype=float)
        if not valid:
            self.hold(now, "pose stream reports no valid pose", auto=True)
            return TargetStatus(False, "pose flagged invalid")
        if not _rigid_ok(T):
            self.hold(now, "invalid target pose (NaN or not a rigid transform)")
            return TargetStatus(False, "target is not a finite rigid 4x4 transform")
        if not np.isfinite(stamp):
            self.hold(now, "target pose has no finite capture stamp", auto=True)
            return TargetStatus(False, "target capture stamp must be a finite time (s)")
        if now - stamp > self.cfg.max_latency_s:
            self.hold(now, f"target pose too old ({now - stamp:.3f} s since capture)", auto=True)
            return TargetStatus(False, "target pose too old")
        if stamp - now > self.cfg.future_stamp_s:
            self.hold(now, f"target capture stamp {stamp - now:.3f} s in the future (clock fault)")
            return TargetStatus(False, "target capture stamp is in the future")
        newest = max(self.target_stamp if self.target is not None else -np.inf,
                     self.pending_stamp if self.pending is not None else -np.inf)
        if stamp < newest:
            return TargetStatus(False, f"target pose older than the current one ({newest - stamp:.3f} s): ignored")
        new_capture = stamp > newest
        if self.target is not None and self.state in (State.TRACKING, State.HOLDING):
            # A jump matters only while the arm follows the target; armed/disarmed, the newest
            # pose simply becomes the reference that start_tracking will use.
            dp = float(np.linalg.norm(T[:3, 3] - self.target[:3, 3]))
            da = float(np.linalg.norm(log3(self.target[:3, :3].T @ T[:3, :3])))
            if dp > self.cfg.jump_m or da > self.cfg.jump_rad:
                self.pending = T.copy()
                self.pending_stamp = float(stamp)
                if new_capture:
                    self.target_received = now
                self.hold(now, f"target jumped {dp*1000:.1f} mm / {np.degrees(da):.1f} deg")
                return TargetStatus(False, f"target jump {dp*1000:.1f} mm / {np.degrees(da):.1f} deg")
        self.target = T.copy()
        self.pending = None
        if new_capture:
            self.target_received = now
        self.target_stamp = float(stamp)
        if self.state == State.HOLDING and self._hold_auto and self.cfg.auto_resume and self.target_fresh(now):
            self._go(State.TRACKING, "fresh valid target again", now)
        return TargetStatus(True, "accepted")

    def target_fresh(self, now: float) -> bool:
        """A newer capture arrived within ``stale_s`` and the newest is at most ``max_latency_s`` old."""
        return (self.target is not None and now - self.target_received <= self.cfg.stale_s
                and now - self.target_stamp <= self.cfg.max_latency_s)

    # ------------------------------------------------------------------ command filter
    def filter_command(self, now: float, q: np.ndarray, dq_des: np.ndarray, dt: float,
                       T_base_tool0: np.ndarray, J_b_tool0: np.ndarray, sigma_min: float,
                       head: HeadSphere | None) -> np.ndarray | None:
        """Limit a tracking command; returns the joint velocity to send (rad/s), or ``None``
        when the arm must be stopped (not tracking, or a fault was found this cycle)."""
        cfg = self.cfg
        if self.state == State.TRACKING:
            if not self.target_fresh(now):
                self.hold(now, f"no fresh valid target (newest capture {now - self.target_stamp:.3f} s old, "
                               f"arrived {now - self.target_received:.3f} s ago)", auto=True)
            elif not np.all(np.isfinite(dq_des)):
                self.hold(now, "controller produced a non-finite command")
            elif sigma_min < cfg.sigma_hold:
                self.hold(now, f"near a singular configuration (sigma_min {sigma_min:.4f})")
        if self.state != State.TRACKING:
            self.last_cmd = np.zeros(6)
            return None
        dq = np.asarray(dq_des, dtype=float).copy()
        # 1. joint speed (uniform scale keeps the direction)
        s = (np.abs(dq) / cfg.joint_speed).max()
        if s > 1.0:
            dq /= s
        # 2. tool speed at the needle tip
        Vt = self._Ad_tip_tool0 @ (J_b_tool0 @ dq)
        s = max(math.sqrt(Vt[3:] @ Vt[3:]) / cfg.tool_speed_m_s, math.sqrt(Vt[:3] @ Vt[:3]) / cfg.tool_angular_rad_s)
        if s > 1.0:
            dq /= s
        # 3. braking before joint position limits
        lo = self.limits.lower + cfg.position_margin_rad
        hi = self.limits.upper - cfg.position_margin_rad
        brake = float(np.max(cfg.joint_speed)) ** 2 / (2.0 * cfg.joint_accel) + 0.01
        if (hi - q).min() < brake or (q - lo).min() < brake:  # near a limit: cap the speed towards it
            vmax_up = np.sqrt(2.0 * cfg.joint_accel * np.clip(hi - q, 0.0, None))
            vmax_dn = np.sqrt(2.0 * cfg.joint_accel * np.clip(q - lo, 0.0, None))
            dq = np.clip(dq, -vmax_dn, vmax_up)
        # 4. keep-out: do not take needle points deeper into the head sphere outside the corridor
        if head is not None and self.target is not None:
            dq = self._keepout(q, dq, T_base_tool0, head)
        # 5. acceleration relative to the last command
        delta = dq - self.last_cmd
        m = np.abs(delta).max()
        lim = cfg.joint_accel * dt
        if m > lim:
            dq = self.last_cmd + delta * (lim / m)
        self.last_cmd = dq
        return dq

    def needle_points(self, T_base_tool0: np.ndarray) -> np.ndarray:
        """Five points along the needle (flange .. tip) in the base frame (m)."""
        return (T_base_tool0 @ self._needle_pts.T).T[:, :3]

    def _keepout(self, q, dq, T_now, head: HeadSphere) -> np.ndarray:
        p_now = self.needle_points(T_now)
        v = self.cfg.tool_speed_m_s
        reach = 2.0 * (v * v / (2.0 * 0.5) + v * self.cfg.keepout_lookahead_s) + self.cfg.keepout_margin_m
        if head.distance(p_now).min() > reach:
            return dq  # nothing near the head: the prediction cannot enter it
        # where the arm would come to rest if it braked now: q + dq * (t_brake / 2 + latency)
        t_brake = float(np.abs(dq).max()) / self.cfg.joint_accel
        q_next = q + dq * (0.5 * t_brake + self.cfg.keepout_lookahead_s)
        T_next = self.kin.fk(q_next)
        p_next = self.needle_points(T_next)
        d_now = head.distance(p_now) - self.cfg.keepout_margin_m
        d_next = head.distance(p_next) - self.cfg.keepout_margin_m
        free = self.corridor.contains(p_next, self.target)
        bad = (d_next < 0) & ~free & (d_next < d_now)
        if bad.any():
            msg = "keep-out: motion towards the head outside the planned path was blocked"
            if not self.warnings or self.warnings[-1] != msg:
                self.warnings.append(msg)
                log.warning(msg)
            return np.zeros(6)
        return dq
