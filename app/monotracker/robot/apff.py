"""6D APFF admittance controller (paper section 2.3.2, Eq. 17-28), three variants.

Frames, units: metres, radians, SI forces. The needle is a segment along tool0 z (see
:class:`~monotracker.robot.kinematics.NeedleTool`): tip ``P_top``, middle ``P_mid``, remote end
``P_rem``. The controlled body frame is the needle's middle frame (paper: ``V^B_mid``). The
target is the desired pose of the needle tip frame, ``T_base_target`` (z = needle direction).
Twists and wrenches are ``(angular; linear)`` as in the paper (Eq. 13, 19), so the parameter
diagonals are read in that order: M = diag(.05,.05,.05, .5,.5,.5) gives the rotational virtual
inertia 0.05 and the translational mass 0.5.

Variants (``variant=``):

* ``"APF-V"``: APF forces mapped straight to velocity, ``V = B^-1 F`` at the measured pose (no
  spring, no mass). Roll about the needle axis is not controlled (a needle is symmetric).
* ``"APF-A-I"``: admittance ``M dV + B V = F + K1 S`` with the APF force always on.
* ``"APF-A-II"`` (paper's method, default): as APF-A-I, but when ``||S|| < epsilon`` the
  stiffness switches to K2 and the APF force is zeroed (multi-segment variable stiffness).

Choices where the paper is silent or inconsistent (written down on purpose):

* Sign: the paper writes ``M dV + B V + K S = F`` with ``S = log(Pose^-1 Tar)``; with that S the
  spring must *pull towards* the target, so we integrate ``M dV = F + K S - B V`` (the stable
  mass-spring-damper form; S is the twist from the pose to the target).
* Eq. 24 integrates a pose: we keep it as a virtual *reference* pose (the admittance model's
  state), initialised from the measured pose, and command the arm with the reference twist plus
  a proportional correction ``kp * log(T_meas^-1 T_ref)`` so arm lag does not enter the
  admittance loop. The reference is re-synchronised to the measured pose when they drift
  apart by more than ``resync_m``/``resync_rad`` (e.g. after the safety layer held the arm).
* The switch back from K2 to K1 happens at ``2 epsilon`` (hysteresis), so a target hovering
  near ``epsilon`` does not chatter between stiffnesses.
* APF constants (zeta, d, eta, rho0, epsilon) are not given in the paper; defaults below are
  chosen so the far-field attractive force gives ~0.13 m/s (conical cap) and repulsion reaches
  several newtons within 1 cm of the head.
* Head repulsion (Khatib, Eq. 18) acts on tip and remote end; points inside the planned-path
  corridor (:class:`~monotracker.robot.head.Corridor`) are exempt, otherwise the needle could
  never reach an entry point on the scalp.
* Joint velocity: damped least squares with the damping raised smoothly as the smallest
  singular value of the body Jacobian falls below ``sigma_min`` (Eq. 25 with a DLS inverse).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

import math

from monotracker.robot.head import Corridor, HeadSphere
from monotracker.robot.kinematics import NeedleTool
from monotracker.robot.lie import adjoint, exp6, inverse, log6, relative

VARIANTS = ("APF-V", "APF-A-I", "APF-A-II")


def _diag(*v):
    return np.diag(np.array(v, dtype=float))


@dataclass
class APFFParams:
    """Controller parameters (SI). Defaults: the paper's Eq. 32 plus the choices in the module doc."""

    M: np.ndarray = field(default_factory=lambda: _diag(0.05, 0.05, 0.05, 0.5, 0.5, 0.5))
    B: np.ndarray = field(default_factory=lambda: _diag(3, 3, 3, 30, 30, 30))
    K1: np.ndarray = field(default_factory=lambda: _diag(10, 10, 10, 10, 10, 10))
    K2: np.ndarray = field(default_factory=lambda: _diag(120, 120, 120, 300, 300, 300))
    #: ||S|| threshold for the stiffness switch (norm of (rad, m) twist).
    epsilon: float = 0.01
    #: Attractive coefficient zeta (N/m) and the quadratic->conical switch distance d (m).
    zeta: float = 100.0
    d: float = 0.02
    #: Repulsive coefficient eta (N m^2) and influence distance rho_0 (m).
    eta: float = 1e-5
    rho0: float = 0.03
    #: Twist saturation of the reference model (m/s, rad/s): anti-windup below the safety limits.
    v_max: float = 0.14
    w_max: float = 0.45
    #: Proportional correction of reference-tracking error (1/s).
    kp: float = 8.0
    resync_m: float = 0.010
    resync_rad: float = np.radians(5.0)
    #: DLS: damping lambda_max applied fully at sigma = 0, fading out at sigma_min.
    sigma_min: float = 0.05
    lambda_max: float = 0.05


@dataclass
class ControlOutput:
    """One controller step. ``dq`` joint velocity command (rad/s); ``S`` the body twist error of
    the reference (rad, m); ``F`` the APF body wrench (N m, N); ``stage`` ``far``/``near``."""

    dq: np.ndarray
    S: np.ndarray
    F: np.ndarray
    V: np.ndarray
    stage: str
    sigma_min: float


def dls_solve(J: np.ndarray, V: np.ndarray, sigma_min: float, lambda_max: float) -> tuple[np.ndarray, float]:
    """``J^+ V`` by damped least squares (via SVD); returns ``(x, smallest singular value)``."""
    U, s, Vt = np.linalg.svd(J)
    smin = float(s[-1])
    lam2 = 0.0 if smin >= sigma_min else lambda_max**2 * (1.0 - (smin / sigma_min) ** 2)
    return Vt.T @ ((s / (s * s + lam2)) * (U.T @ V)), smin


def attractive_force(p: np.ndarray, p_goal: np.ndarray, zeta: float, d: float) -> np.ndarray:
    """Paper Eq. 17: quadratic well within ``d`` of the goal, conical (|F| = zeta d) beyond (N)."""
    e = p - p_goal
    n = math.sqrt(e @ e)
    if n <= d:
        return -zeta * e
    return -d * zeta * e / n


def repulsive_force(p: np.ndarray, head: HeadSphere, eta: float, rho0: float) -> np.ndarray:
    """Paper Eq. 18 (Khatib): ``eta (1/rho - 1/rho0) / rho^2 * grad(rho)`` within ``rho0`` (N).
    ``rho`` is the distance to the sphere surface, floored at 1 mm (inside the sphere the force
    keeps pushing outwards at its 1 mm value rather than becoming infinite or flipping)."""
    r = p - head.centre_m
    dist = math.sqrt(r @ r)
    rho = dist - head.radius_m
    if rho > rho0 or dist < 1e-9:
        return np.zeros(3)
    rho = max(rho, 1e-3)
    return eta * (1.0 / rho - 1.0 / rho0) / rho**2 * (r / dist)


def point_wrench_space(r: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Paper Eq. 19: wrench ``(r x f; f)`` of a force ``f`` at point ``r`` (base frame)."""
    return np.array([r[1] * f[2] - r[2] * f[1], r[2] * f[0] - r[0] * f[2], r[0] * f[1] - r[1] * f[0],
                     f[0], f[1], f[2]])


class APFFController:
    """Stateful controller; call :meth:`reset` whenever tracking (re)starts."""

    def __init__(self, variant: str = "APF-A-II", params: APFFParams | None = None,
                 tool: NeedleTool | None = None, corridor: Corridor | None = None):
        if variant not in VARIANTS:
            raise ValueError(f"unknown APFF variant {variant!r}; choose one of {', '.join(VARIANTS)}")
        self.variant = variant
        self.p = params or APFFParams()
        self.tool = tool or NeedleTool()
        self.corridor = corridor or Corridor()
        self.head: HeadSphere | None = None
        for name in ("M", "B", "K1", "K2"):
            m = np.asarray(getattr(self.p, name), dtype=float)
            if m.shape != (6, 6) or not np.allclose(m, np.diag(np.diag(m))) or np.any(np.diag(m) < 0):
                raise ValueError(f"APFF {name} must be a non-negative diagonal 6x6 matrix")
        if np.any(np.diag(self.p.M) <= 0) or np.any(np.diag(self.p.B) <= 0):
            raise ValueError("APFF M and B must be positive")
        # Diagonal parameters as vectors: element-wise products in the hot path.
        self._m = np.diag(self.p.M).copy()
        self._b = np.diag(self.p.B).copy()
        self._k1 = np.diag(self.p.K1).copy()
        self._k2 = np.diag(self.p.K2).copy()
        X = self.tool.T_tool0_mid
        self._T_tool0_mid = X
        self._T_mid_tip = inverse(X) @ self.tool.T_tool0_tip
        self._T_tip_mid = inverse(self._T_mid_tip)
        self._Ad_mid_tip = adjoint(self._T_mid_tip)
        self._Ad_mid_tool0 = adjoint(inverse(X))
        half = 0.5 * self.tool.length_m
        self._half = half
        self.reset()

    def reset(self) -> None:
        self.T_ref: np.ndarray | None = None
        self.V = np.zeros(6)
        self.near = False

    # ------------------------------------------------------------------ pieces
    def target_mid(self, T_base_target: np.ndarray) -> np.ndarray:
        """Desired mid frame from the desired tip frame."""
        return T_base_target @ self._T_tip_mid

    def apf_wrench_body(self, T_mid: np.ndarray, T_mid_goal: np.ndarray, T_base_target: np.ndarray) -> np.ndarray:
        """Paper Eq. 19-21: attractive + repulsive forces on tip and remote end, as wrenches
        ``(r x f; f)`` in the base frame, mapped to the body (mid) frame with ``Ad(T_base_mid)^T``
        and summed. Evaluated directly in the mid frame (``Ad^T (r x f; f) = (r_b x f_b; f_b)``
        with ``r_b``, ``f_b`` the point and force in mid coordinates), which is the same number
        with fewer operations; the test suite checks it against the written-out Eq. 19-21."""
        p = self.p
        R = T_mid[:3, :3]
        z = R[:, 2]
        h = self._half
        P = np.array([T_mid[:3, 3] + h * z, T_mid[:3, 3] - h * z])
        zg = T_mid_goal[:3, 2]
        G = (T_mid_goal[:3, 3] + h * zg, T_mid_goal[:3, 3] - h * zg)
        exempt = None if self.head is None else self.corridor.contains(P, T_base_target)
        F = np.zeros(6)
        for k, sign in ((0, 1.0), (1, -1.0)):
            f = attractive_force(P[k], G[k], p.zeta, p.d)
            if exempt is not None and not exempt[k]:
                f = f + repulsive_force(P[k], self.head, p.eta, p.rho0)
            fb = R.T @ f
            # r_b = (0, 0, sign*h): r_b x f_b = sign*h*(-fb_y, fb_x, 0)
            F[0] -= sign * h * fb[1]
            F[1] += sign * h * fb[0]
            F[3:] += fb
        return F

    def _saturate(self, V: np.ndarray) -> np.ndarray:
        w = math.sqrt(V[:3] @ V[:3])
        v = math.sqrt(V[3:] @ V[3:])
        out = V.copy()
        if w > self.p.w_max:
            out[:3] *= self.p.w_max / w
        if v > self.p.v_max:
            out[3:] *= self.p.v_max / v
        return out

    # ------------------------------------------------------------------ step
    def step(self, T_base_tool0: np.ndarray, J_b_tool0: np.ndarray, dq_meas: np.ndarray,
             T_base_target: np.ndarray, dt: float, V_target: np.ndarray | None = None) -> ControlOutput:
        """One control period: measured flange pose and body Jacobian (tool0), measured joint
        rates, the desired tip pose, period ``dt`` (s) -> joint velocity command (rad/s).

        ``V_target`` (optional, an extension beyond the paper): the target's own body twist
        (tip frame, ``(omega, v)``), e.g. estimated from the pose stream. When given, the
        damper acts on the velocity *relative* to the moving target, ``B (V - V_t)``, and APF-V
        adds it to its output; without it the controller is exactly the paper's."""
        p = self.p
        V_ff = None if V_target is None else self._Ad_mid_tip @ np.asarray(V_target, dtype=float)
        T_mid = T_base_tool0 @ self._T_tool0_mid
        J_mid = self._Ad_mid_tool0 @ J_b_tool0
        T_goal = self.target_mid(T_base_target)

        if self.variant == "APF-V":
            S = log6(relative(T_mid, T_goal))
            F = self.apf_wrench_body(T_mid, T_goal, T_base_target)
            self.V = self._saturate(F / self._b if V_ff is None else F / self._b + V_ff)
            dq, smin = dls_solve(J_mid, self.V, p.sigma_min, p.lambda_max)
            return ControlOutput(dq, S, F, self.V.copy(), "far", smin)

        if self.T_ref is None:
            self.T_ref = T_mid.copy()
            self.V = J_mid @ dq_meas
        else:
            drift = log6(relative(T_mid, self.T_ref))
            if drift[3:] @ drift[3:] > p.resync_m**2 or drift[:3] @ drift[:3] > p.resync_rad**2:
                self.T_ref = T_mid.copy()
                self.V = J_mid @ dq_meas

        S = log6(relative(self.T_ref, T_goal))
        nS = math.sqrt(S @ S)
        if self.variant == "APF-A-II":
            if self.near and nS > 2.0 * p.epsilon:
                self.near = False
            elif not self.near and nS < p.epsilon:
                self.near = True
        if self.near:
            F = np.zeros(6)
            k = self._k2
        else:
            F = self.apf_wrench_body(self.T_ref, T_goal, T_base_target)
            k = self._k1
        # Semi-implicit Euler (Eq. 24): velocity first, then the reference pose.
        damp = self._b * (self.V if V_ff is None else self.V - V_ff)
        self.V = self._saturate(self.V + dt * (F + k * S - damp) / self._m)
        # Command: reference twist seen from the measured frame + correction towards the
        # reference *now* (the pose measured at the start of this period against the reference
        # for the same instant; the one integrated below is for the end of the period, and
        # correcting towards it would put the arm one period ahead of its reference)
        T_err = relative(T_mid, self.T_ref)
        self.T_ref = self.T_ref @ exp6(self.V * dt)
        V_cmd = adjoint(T_err) @ self.V + p.kp * log6(T_err)
        dq, smin = dls_solve(J_mid, V_cmd, p.sigma_min, p.lambda_max)
        return ControlOutput(dq, S, F, self.V.copy(), "near" if self.near else "far", smin)
