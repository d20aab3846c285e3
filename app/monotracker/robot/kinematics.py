"""UR10 kinematics: pinocchio model from ``example-robot-data`` plus the paper's product of
exponentials (POE, paper Eq. 13-16) written out, and the needle tool frame.

Frames and units: metres and radians. ``base`` is the UR10 ``base_link`` frame of the URDF,
``tool0`` the flange frame. The needle (puncture device) is rigid on the flange: its tip lies on
the tool0 z axis at ``needle_length_m`` (plus an optional fixed offset), its remote end at the
flange, the middle point half-way. Frames ``tip`` and ``mid`` share tool0's orientation.

Twists are ``(omega, v)`` (see :mod:`monotracker.robot.lie`). The body Jacobian ``J_b`` maps
joint rates to the twist of tool0 expressed in tool0; the space Jacobian ``J_s`` to the twist
expressed in the base frame (pinocchio calls them LOCAL and WORLD).

The POE model uses the joint axes and points of the URDF at q = 0 (numbers below, read off
``ur10_robot.urdf``): ``T(q) = exp([S1] q1) ... exp([S6] q6) M``. ``tests/robot`` checks it
against pinocchio to 1e-9 over random configurations.
"""

from __future__ import annotations

import functools
import importlib.util
import pathlib
import sysconfig
from dataclasses import dataclass

import numpy as np

from monotracker.errors import MonoTrackerError
from monotracker.geometry import invert_transform
from monotracker.robot.lie import adjoint, adjoint_ref, exp6_ref, hat, log6

URDF_RELATIVE = pathlib.Path("cmeel.prefix/share/example-robot-data/robots/ur_description/urdf/ur10_robot.urdf")
TOOL_FRAME = "tool0"

# ------------------------------------------------------------------------- POE constants
#: Joint axes (base frame, unit) at q = 0.
POE_AXES = np.array(
    [[0, 0, 1], [0, 1, 0], [0, 1, 0], [0, 1, 0], [0, 0, -1], [0, 1, 0]], dtype=float
)
#: A point on each joint axis (base frame, m) at q = 0.
POE_POINTS = np.array(
    [
        [0.0, 0.0, 0.1273],
        [0.0, 0.220941, 0.1273],
        [0.612, 0.049041, 0.1273],
        [1.1843, 0.049041, 0.1273],
        [1.1843, 0.163941, 0.1273],
        [1.1843, 0.163941, 0.0116],
    ]
)
#: tool0 pose at q = 0 (base frame).
POE_HOME = np.array(
    [[-1.0, 0.0, 0.0, 1.1843], [0.0, 0.0, 1.0, 0.256141], [0.0, 1.0, 0.0, 0.0116], [0, 0, 0, 1.0]]
)
#: Spatial screw axes ``S_i = (omega_i; -omega_i x r_i)`` (paper Eq. 13), rows.
POE_SCREWS = np.hstack([POE_AXES, -np.cross(POE_AXES, POE_POINTS)])

#: A configuration with the flange pointing down, ~0.6 m in front of the base (used by tests,
#: benchmarks and as the IK seed). Elbow up, wrist clear of singularities.
Q_READY = np.array([0.0, -1.9, 1.9, -1.57, -1.57, 0.0])


def urdf_path() -> pathlib.Path:
    """Location of ``ur10_robot.urdf`` shipped by the example-robot-data wheel (as data)."""
    roots = []
    spec = importlib.util.find_spec("pinocchio")
    if spec and spec.origin:
        roots.append(pathlib.Path(spec.origin).resolve().parents[1])
    for key in ("purelib", "platlib"):
        roots.append(pathlib.Path(sysconfig.get_paths()[key]))
    for root in roots:
        for base in (root, *root.parents[:4]):
            p = base / URDF_RELATIVE
            if p.is_file():
                return p
    raise MonoTrackerError(
        "ur10_robot.urdf not found: install the 'example-robot-data' package into this Python"
    )


@functools.lru_cache(maxsize=1)
def _model():
    import pinocchio as pin

    model = pin.buildModelFromUrdf(str(urdf_path()))
    return model, model.getFrameId(TOOL_FRAME)


@dataclass(frozen=True)
class JointLimits:
    """UR10 joint limits (rad, rad/s, rad/s^2). Position/velocity from the URDF; acceleration
    is a conservative choice (the URDF has none; UR's default joint acceleration is 1.4)."""

    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray


def joint_limits() -> JointLimits:
    model, _ = _model()
    return JointLimits(
        lower=np.array(model.lowerPositionLimit, dtype=float),
        upper=np.array(model.upperPositionLimit, dtype=float),
        velocity=np.array(model.velocityLimit, dtype=float),
        acceleration=np.full(6, 4.0),
    )


class Kinematics:
    """Pinocchio-backed UR10 kinematics with its own data buffer (one per thread)."""

    def __init__(self):
        import pinocchio as pin

        self._pin = pin
        self.model, self.tool_id = _model()
        self.data = self.model.createData()

    def fk(self, q: np.ndarray) -> np.ndarray:
        """``T_base_tool0`` (4,4), m."""
        pin = self._pin
        pin.framesForwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        return self.data.oMf[self.tool_id].homogeneous.copy()

    def fk_and_jacobian_body(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(T_base_tool0, J_b)`` in one pass; ``J_b`` (6,6) with rows ``(omega, v)`` in tool0."""
        pin = self._pin
        q = np.asarray(q, dtype=float)
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        J = pin.getFrameJacobian(self.model, self.data, self.tool_id, pin.ReferenceFrame.LOCAL)
        # pinocchio orders (v, omega); we use (omega, v).
        return self.data.oMf[self.tool_id].homogeneous.copy(), np.vstack([J[3:], J[:3]])

    def jacobian_body(self, q: np.ndarray) -> np.ndarray:
        return self.fk_and_jacobian_body(q)[1]

    def jacobian_space(self, q: np.ndarray) -> np.ndarray:
        """``J_s`` (6,6): joint rates -> tool twist expressed in the base frame."""
        T, Jb = self.fk_and_jacobian_body(q)
        return adjoint(T) @ Jb


_default: Kinematics | None = None


def _kin() -> Kinematics:
    global _default
    if _default is None:
        _default = Kinematics()
    return _default


def fk(q: np.ndarray) -> np.ndarray:
    """Forward kinematics ``T_base_tool0`` (4,4) in metres (pinocchio)."""
    return _kin().fk(q)


def jacobian_body(q: np.ndarray) -> np.ndarray:
    """Body Jacobian of tool0 (6,6), twist order ``(omega, v)`` in the tool0 frame."""
    return _kin().jacobian_body(q)


def jacobian_space(q: np.ndarray) -> np.ndarray:
    """Space Jacobian of tool0 (6,6), twist order ``(omega, v)`` in the base frame."""
    return _kin().jacobian_space(q)


# ------------------------------------------------------------------------- POE (paper)
def poe_fk(q: np.ndarray) -> np.ndarray:
    """Paper Eq. 14: ``T = exp([S1]q1) ... exp([S6]q6) M`` (base -> tool0, m)."""
    T = np.eye(4)
    for S, qi in zip(POE_SCREWS, q):
        T = T @ exp6_ref(S * qi)
    return T @ POE_HOME


def poe_jacobian_space(q: np.ndarray) -> np.ndarray:
    """Paper Eq. 15-16: column i is ``Ad(exp([S1]q1)...exp([S_{i-1}]q_{i-1})) S_i``."""
    J = np.zeros((6, 6))
    T = np.eye(4)
    for i, (S, qi) in enumerate(zip(POE_SCREWS, q)):
        J[:, i] = adjoint_ref(T) @ S
        T = T @ exp6_ref(S * qi)
    return J


def poe_jacobian_body(q: np.ndarray) -> np.ndarray:
    """``J_b = Ad(T_base_tool0^-1) J_s``."""
    return adjoint_ref(invert_transform(poe_fk(q))) @ poe_jacobian_space(q)


# ------------------------------------------------------------------------- needle tool
@dataclass(frozen=True)
class NeedleTool:
    """The puncture device on the flange, as a segment along tool0 z.

    ``length_m``: flange (remote end) to tip. ``offset_m``: a fixed shift of the segment along
    tool z (e.g. an adapter plate), default 0. Default length 0.20 m (paper: a puncture device
    with a needle guide; the exact length is not given).
    """

    length_m: float = 0.20
    offset_m: float = 0.0

    def __post_init__(self):
        if not (np.isfinite(self.length_m) and self.length_m > 0):
            raise MonoTrackerError(f"needle length must be > 0 m, got {self.length_m}")

    @property
    def T_tool0_tip(self) -> np.ndarray:
        T = np.eye(4)
        T[2, 3] = self.offset_m + self.length_m
        return T

    @property
    def T_tool0_mid(self) -> np.ndarray:
        T = np.eye(4)
        T[2, 3] = self.offset_m + 0.5 * self.length_m
        return T

    @property
    def T_tool0_remote(self) -> np.ndarray:
        T = np.eye(4)
        T[2, 3] = self.offset_m
        return T


# ------------------------------------------------------------------------- IK
@dataclass
class IKResult:
    ok: bool
    reason: str
    q: np.ndarray
    position_error_m: float
    angle_error_rad: float
    iterations: int


def ik(
    T_base_tool_target: np.ndarray,
    q0: np.ndarray | None = None,
    T_tool0_tool: np.ndarray | None = None,
    max_iter: int = 200,
    tol_m: float = 1e-6,
    tol_rad: float = 1e-6,
    damping: float = 1e-3,
    kin: Kinematics | None = None,
) -> IKResult:
    """Damped least-squares IK (body-frame Newton steps on ``log(T^-1 T_target)``).

    ``T_base_tool_target`` (4,4, m) is the desired pose of the frame ``tool0 @ T_tool0_tool``
    (identity: tool0 itself; pass ``NeedleTool().T_tool0_tip`` to place the needle tip).
    Stays within the joint position limits (solutions are clipped, then re-iterated).
    Returns ``ok=False`` with a reason when it does not converge (unreachable or too far from
    ``q0``): never a silently wrong configuration.
    """
    kin = kin or _kin()
    lim = joint_limits()
    q = np.array(Q_READY if q0 is None else q0, dtype=float)
    Tt = np.eye(4) if T_tool0_tool is None else np.asarray(T_tool0_tool, dtype=float)
    Ad_tt = adjoint(invert_transform(Tt))
    target = np.asarray(T_base_tool_target, dtype=float)
    if target.shape != (4, 4) or not np.all(np.isfinite(target)):
        return IKResult(False, "target pose is not a finite 4x4 transform", q, np.inf, np.inf, 0)
    err = np.full(6, np.inf)
    for it in range(1, max_iter + 1):
        T0, Jb0 = kin.fk_and_jacobian_body(q)
        T = T0 @ Tt
        err = log6(invert_transform(T) @ target)
        if np.linalg.norm(err[:3]) < tol_rad and np.linalg.norm(T[:3, :3].T @ (target[:3, 3] - T[:3, 3])) < tol_m:
            return IKResult(True, "converged", q, float(np.linalg.norm(target[:3, 3] - T[:3, 3])),
                            float(np.linalg.norm(err[:3])), it)
        J = Ad_tt @ Jb0
        step = J.T @ np.linalg.solve(J @ J.T + damping**2 * np.eye(6), err)
        n = np.linalg.norm(step)
        if n > 0.5:
            step *= 0.5 / n
        q = np.clip(q + step, lim.lower, lim.upper)
    T = kin.fk(q) @ Tt
    pe = float(np.linalg.norm(target[:3, 3] - T[:3, 3]))
    return IKResult(False, f"IK did not converge (residual {pe*1000:.2f} mm, "
                    f"{np.degrees(np.linalg.norm(err[:3])):.2f} deg): target unreachable from this start",
                    q, pe, float(np.linalg.norm(err[:3])), max_iter)


def manipulability(Jb: np.ndarray) -> float:
    """Smallest singular value of a Jacobian (0 at a singularity)."""
    return float(np.linalg.svd(Jb, compute_uv=False)[-1])


__all__ = [
    "fk", "jacobian_body", "jacobian_space", "poe_fk", "poe_jacobian_space", "poe_jacobian_body",
    "Kinematics", "NeedleTool", "ik", "IKResult", "joint_limits", "JointLimits", "Q_READY",
    "urdf_path", "manipulability", "hat",
]
