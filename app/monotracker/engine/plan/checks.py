"""One validation per kind of plan state, used by every way that state enters.

A command (``Session.set_entry``, ``add_fiducial``, ``set_hand_eye``, ``confirm_fiducials``, the
camera the loop stores: :mod:`~monotracker.engine.plan.editor`), a restored ``plan.json``
(:mod:`~monotracker.engine.plan.store`) and the arming gate all call the functions here, so what a
setter refuses, a restore refuses too.

Each check returns ``None`` when the value is acceptable, else a one-line reason the operator can
act on. Units: CT LPS millimetres, pixels for the camera, degrees for angles.

Checks that need the CT (skin surface, head interior, volume bounds, the density of an added
fiducial) take an :class:`Anatomy`; without one they report themselves as not checked
(:func:`path_unchecked_reason`) rather than passing silently.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from monotracker.engine.plan.model import ROLES, STATUSES, angle_to_skin_normal_deg


@dataclass(frozen=True)
class PlanLimits:
    """Sane ranges (choices written down here; the paper leaves them open).

    ``rigid_tol``: max |R^T R - I| and |det R - 1| of a hand-eye rotation. ``max_translation_mm``:
    the camera is within this distance of the robot base (a UR10 reaches 1.3 m; 3 m is generous).
    ``radius_mm``: fiducial radius range. ``entry_skin_mm``: the entry lies within this distance
    of the skin surface. ``path_mm``: path length range. ``max_angle_deg``: max angle between the
    needle and the outward skin normal at the entry. ``fiducial_clearance_mm``: the path keeps this
    distance from the surface of every fiducial ball. ``ball_contrast_hu``: an added fiducial needs
    its ball's mean HU this much above the shell around it.
    """

    rigid_tol: float = 1e-6
    max_translation_mm: float = 3000.0
    radius_mm: tuple = (0.5, 25.0)
    entry_skin_mm: float = 5.0
    path_mm: tuple = (5.0, 150.0)
    max_angle_deg: float = 60.0
    fiducial_clearance_mm: float = 2.0
    ball_contrast_hu: float = 300.0


LIMITS = PlanLimits()


@dataclass
class Anatomy:
    """What the CT tells the checks: the volume (``monotracker.ct.Volume``, LPS mm), the skin
    mesh vertices (n, 3) LPS mm and outward vertex normals (n, 3), and ``skin_hu``, the HU level
    between air and soft tissue (voxels above it are inside the head)."""

    volume: object
    vertices: np.ndarray | None
    normals: np.ndarray | None
    skin_hu: float
    levels: dict = field(default_factory=dict)

    @classmethod
    def from_ct(cls, volume, mesh=None) -> "Anatomy":
        """Build from a loaded volume and its ``head_surface`` mesh (None: no surface)."""
        from monotracker.ct.fiducials import estimate_levels

        lv = estimate_levels(volume)
        verts = None if mesh is None else np.asarray(mesh.vertices, float)
        normals = None if mesh is None else np.asarray(mesh.vertex_normals, float)
        return cls(volume, verts, normals, 0.5 * (lv["air"] + lv["tissue"]), lv)

    # -------------------------------------------------------------- queries
    def in_volume(self, p) -> bool:
        ijk = self.volume.lps_to_index(np.asarray(p, float).reshape(1, 3))[0]
        size = np.asarray(self.volume.size_ijk, float)
        return bool(np.all(ijk >= -0.5) and np.all(ijk <= size - 0.5))

    def hu_at(self, p) -> float | None:
        """HU of the voxel nearest ``p`` (LPS mm), None outside the volume."""
        if not self.in_volume(p):
            return None
        ijk = np.rint(self.volume.lps_to_index(np.asarray(p, float).reshape(1, 3))[0]).astype(int)
        ijk = np.clip(ijk, 0, np.asarray(self.volume.size_ijk) - 1)
        return float(self.volume.array[ijk[2], ijk[1], ijk[0]])

    def skin_distance_mm(self, p) -> float | None:
        """Distance (mm) from ``p`` to the nearest skin-mesh vertex; None without a surface."""
        if self.vertices is None or len(self.vertices) == 0:
            return None
        return float(np.min(np.linalg.norm(self.vertices - np.asarray(p, float), axis=1)))

    def ball_contrast(self, centre, radius_mm: float) -> tuple[float, float] | None:
        """(mean HU inside the ball, mean HU in the shell from r + 1 to r + 4 mm); None when the
        ball is not inside the volume."""
        vol = self.volume
        c = np.asarray(centre, float)
        reach = radius_mm + 4.0
        corners = c + reach * np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        if not all(self.in_volume(q) for q in corners):
            return None
        ijk = vol.lps_to_index(corners)
        lo = np.maximum(np.floor(ijk.min(axis=0)).astype(int), 0)
        hi = np.minimum(np.ceil(ijk.max(axis=0)).astype(int) + 1, np.asarray(vol.size_ijk))
        ii, jj, kk = np.meshgrid(*(np.arange(a, b) for a, b in zip(lo, hi)), indexing="ij")
        idx = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], axis=1)
        d = np.linalg.norm(vol.index_to_lps(idx) - c, axis=1)
        vals = vol.array[idx[:, 2], idx[:, 1], idx[:, 0]].astype(float)
        inside = vals[d <= max(radius_mm * 0.7, 0.5)]
        shell = vals[(d >= radius_mm + 1.0) & (d <= radius_mm + 4.0)]
        if inside.size == 0 or shell.size == 0:
            return None
        return float(inside.mean()), float(shell.mean())


# ---------------------------------------------------------------------- primitive values
def finite_array(v, shape: tuple, what: str) -> tuple[np.ndarray | None, str | None]:
    """(array, None) when ``v`` is numeric of ``shape`` and finite, else (None, reason)."""
    if isinstance(v, (str, bytes, dict)) or isinstance(v, bool):
        return None, f"{what} must be numbers of shape {shape}, not {type(v).__name__}"
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        return None, f"{what} must be numbers of shape {shape}"
    if a.shape != shape:
        return None, f"{what} has shape {a.shape}, expected {shape}"
    if not np.all(np.isfinite(a)):
        return None, f"{what} has a non-finite value"
    return a, None


def real_number(v, what: str) -> tuple[float | None, str | None]:
    """(float, None) for a finite int/float (not bool, not a string), else (None, reason)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        return None, f"{what} must be a number, not {type(v).__name__}"
    x = float(v)
    if not math.isfinite(x):
        return None, f"{what} must be finite, not {x}"
    return x, None


# ---------------------------------------------------------------------- hand-eye
def check_hand_eye(T, limits: PlanLimits = LIMITS) -> str | None:
    """``T_base_cam`` (4x4, mm): finite, a rotation (orthonormal, det +1) and a sane translation."""
    a, why = finite_array(T, (4, 4), "T_base_cam")
    if why:
        return why
    from monotracker.robot.rigid import rigid_problem  # the one rigid check (robot targets, hand-eye)

    why = rigid_problem(a, limits.rigid_tol, "T_base_cam")
    if why:
        return why
    if np.abs(a[:3, 3]).max() > limits.max_translation_mm:  # before the norm: no overflow
        return f"T_base_cam puts the camera more than {limits.max_translation_mm:.0f} mm from the robot base"
    t = float(np.linalg.norm(a[:3, 3]))
    if t > limits.max_translation_mm:
        return f"T_base_cam puts the camera {t:.0f} mm from the robot base (max {limits.max_translation_mm:.0f} mm)"
    return None


# ---------------------------------------------------------------------- fiducials
def check_fiducial(fid_id, centre, radius_mm, score, status, limits: PlanLimits = LIMITS) -> str | None:
    """One fiducial: integer id, finite centre (3,) LPS mm, radius in range, score 0..1, known status."""
    if isinstance(fid_id, bool) or not isinstance(fid_id, (int, np.integer)) or fid_id < 0:
        return f"fiducial id must be a non-negative integer, not {fid_id!r}"
    _, why = check_point(centre, f"fiducial {fid_id} centre")
    if why:
        return why
    r, why = real_number(radius_mm, f"fiducial {fid_id} radius")
    if why:
        return why
    if not (limits.radius_mm[0] <= r <= limits.radius_mm[1]):
        return f"fiducial {fid_id} radius {r:g} mm is outside {limits.radius_mm[0]:g}..{limits.radius_mm[1]:g} mm"
    s, why = real_number(score, f"fiducial {fid_id} score")
    if why:
        return why
    if not (0.0 <= s <= 1.0):
        return f"fiducial {fid_id} score {s:g} is outside 0..1"
    if status not in STATUSES:
        return f"fiducial {fid_id} has unknown status {status!r}"
    return None


def check_fiducial_kit(radius_mm, density_hu=None) -> str | None:
    """The fiducial kit: radius (mm) and optional density (HU), finite numbers in the ranges of
    :class:`monotracker.ct.kit.FiducialKit` (the one place they are written down; a restored
    plan's kit goes through the same class)."""
    from monotracker.ct.kit import FiducialKit

    if radius_mm is None:
        return "the fiducial kit needs the balls' radius (mm)"
    try:
        FiducialKit(radius_mm, density_hu)
    except ValueError as exc:
        return str(exc)
    return None


def check_ball_finish(finish) -> str | None:
    """The kit's balls' finish: one of vision's words for it
    (:data:`monotracker.vision.ball_gloss.FINISHES`: read, matte, glossy)."""
    from monotracker.vision.ball_gloss import FINISHES

    if not isinstance(finish, str) or finish not in FINISHES:
        return f"ball finish must be one of {', '.join(FINISHES)}, not {finish!r}"
    return None


def check_fiducial_set(fiducials) -> str | None:
    """Unique ids; no two usable balls overlapping."""
    ids = [f.id for f in fiducials]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        return f"fiducial ids repeat: {dup}"
    use = [f for f in fiducials if f.status in ("confirmed", "added")]
    for i, a in enumerate(use):
        for b in use[i + 1:]:
            d = float(np.linalg.norm(np.asarray(a.centre_lps_mm) - np.asarray(b.centre_lps_mm)))
            if d < a.radius_mm + b.radius_mm:
                return f"fiducials {a.id} and {b.id} overlap ({d:.1f} mm apart)"
    return None


def check_locked(plan, min_usable: int) -> str | None:
    """A locked set must hold >= ``min_usable`` usable fiducials; the flag must be a real bool."""
    if not isinstance(plan.fiducials_locked, bool):
        return f"fiducials_locked must be true or false, not {plan.fiducials_locked!r}"
    if plan.fiducials_locked:
        n = len(plan.usable_fiducials())
        if n < min_usable:
            return f"fiducial set is locked with {n} usable fiducials; at least {min_usable} are needed"
        n_reg = len(plan.registration_fiducials())
        if n_reg < min_usable:
            return (f"{n_reg} usable fiducials have the registration role (the rest validate it); "
                    f"at least {min_usable} are needed")
    return None


def check_role(fid, role) -> str | None:
    """A fiducial's role: ``"registration"`` (in the fit) or ``"validation"`` (kept out, verifies it)."""
    if role not in ROLES:
        return f"fiducial {fid} role must be registration or validation, not {role!r}"
    return None


def check_added_fiducial(anatomy: Anatomy | None, centre, radius_mm: float,
                         limits: PlanLimits = LIMITS) -> tuple[bool | None, str]:
    """Is there a dense ball of ``radius_mm`` at ``centre`` in the CT?

    Returns ``(True, why)`` verified, ``(False, why)`` the CT shows no such ball there, or
    ``(None, why)`` not checkable (no CT loaded, the ball leaves the volume)."""
    if anatomy is None:
        return None, "no CT loaded to check it against"
    # the CT's own judgement (a ball that the detection would accept there), not a mean contrast:
    # a point inside the skull passed that as a "verified ball" (issue 36)
    from monotracker.ct.ball_check import check_ball_at

    res = check_ball_at(anatomy.volume, centre, radius_mm, anatomy.levels, limits.ball_contrast_hu)
    if res.outside:
        return None, res.why
    return res.verified, res.why


# ---------------------------------------------------------------------- path
#: No CT point lies farther than this from the scanner's origin (mm): a sanity bound.
MAX_COORD_MM = 10000.0


def check_point(p, what: str) -> tuple[np.ndarray | None, str | None]:
    """(point, None) for three finite coordinates within +-:data:`MAX_COORD_MM` (LPS mm), else (None, reason)."""
    a, why = finite_array(p, (3,), what)
    if why:
        return None, why
    if np.abs(a).max() > MAX_COORD_MM:
        return None, f"{what} lies more than {MAX_COORD_MM / 1000:g} m from the CT origin"
    return a, None


def check_entry_target_pair(entry, target, limits: PlanLimits = LIMITS) -> str | None:
    """CT-free checks of the path: distinct points, length in range."""
    if entry is None or target is None:
        return None
    L = float(np.linalg.norm(np.asarray(target, float) - np.asarray(entry, float)))
    if L < 1.0:
        return "entry and target must be at least 1 mm apart"
    if not (limits.path_mm[0] <= L <= limits.path_mm[1]):
        return f"path length {L:.1f} mm is outside {limits.path_mm[0]:g}..{limits.path_mm[1]:g} mm"
    return None


def check_entry_anatomy(entry, anatomy: Anatomy, limits: PlanLimits = LIMITS) -> str | None:
    d = anatomy.skin_distance_mm(entry)
    if d is None:
        return None
    if d > limits.entry_skin_mm:
        where = "inside the head" if (anatomy.hu_at(entry) or -1e9) > anatomy.skin_hu else "away from the head"
        return f"entry is {d:.1f} mm from the skin surface ({where}); it must be within {limits.entry_skin_mm:g} mm"
    return None


def check_target_anatomy(target, anatomy: Anatomy) -> str | None:
    if not anatomy.in_volume(target):
        return "target is outside the CT volume"
    hu = anatomy.hu_at(target)
    if hu is None or hu <= anatomy.skin_hu:
        return f"target is not inside the head (CT reads {hu:.0f} HU there: air)"
    return None


def _segment_clearance(entry, target, fiducials) -> tuple[float, int] | None:
    """(smallest distance from the segment to a usable fiducial's ball surface, its id)."""
    use = [f for f in fiducials if f.status in ("confirmed", "added")]
    if not use:
        return None
    a, b = np.asarray(entry, float), np.asarray(target, float)
    ab = b - a
    L2 = float(ab @ ab)
    best = None
    for f in use:
        c = np.asarray(f.centre_lps_mm, float)
        s = 0.0 if L2 == 0 else float(np.clip((c - a) @ ab / L2, 0.0, 1.0))
        gap = float(np.linalg.norm(c - (a + s * ab))) - float(f.radius_mm)
        if best is None or gap < best[0]:
            best = (gap, f.id)
    return best


def check_path(entry, target, fiducials, anatomy: Anatomy | None, limits: PlanLimits = LIMITS) -> str | None:
    """Every path check that can run: pair, fiducial clearance, and with a CT the skin, head,
    volume and angle checks. The first failure, or None."""
    why = check_entry_target_pair(entry, target, limits)
    if why:
        return why
    if entry is None or target is None:
        return None
    cl = _segment_clearance(entry, target, fiducials)
    if cl is not None and cl[0] < limits.fiducial_clearance_mm:
        return f"the path passes {max(cl[0], 0.0):.1f} mm from fiducial {cl[1]} (needs {limits.fiducial_clearance_mm:g} mm)"
    if anatomy is None:
        return None
    why = check_entry_anatomy(entry, anatomy, limits) or check_target_anatomy(target, anatomy)
    if why:
        return why
    ang = angle_to_normal_deg(entry, target, anatomy)
    if ang is not None and ang > limits.max_angle_deg:
        return f"the needle meets the skin at {ang:.0f} deg from its normal (max {limits.max_angle_deg:g} deg)"
    return None


def angle_to_normal_deg(entry, target, anatomy: Anatomy) -> float | None:
    if anatomy.vertices is None:
        return None
    return angle_to_skin_normal_deg(entry, target, anatomy.vertices, anatomy.normals)


def path_unchecked_reason(plan, anatomy: Anatomy | None) -> str | None:
    """Why the CT-dependent path checks did not run (None when they did or there is no path)."""
    if not plan.path_complete:
        return None
    if anatomy is None:
        return "no CT loaded: skin, head interior and volume checks of the path not run"
    return None


# ---------------------------------------------------------------------- camera
def check_camera(K, dist, image_size) -> str | None:
    """Intrinsics ``K`` (3x3 px), distortion ``dist`` (OpenCV order), ``image_size`` (width,
    height) px, as the plan stores them. All None: no camera yet. Types are checked here, the
    values by vision's :func:`~monotracker.vision.camera_model.validate_intrinsics` (the one
    intrinsics check: positive focal lengths, principal point inside the image, finite, a known
    number of distortion coefficients)."""
    if K is None and dist is None and image_size is None:
        return None
    if K is None or image_size is None:
        return "camera K and image_size must be stored together"
    Ka, why = finite_array(K, (3, 3), "camera K")
    if why:
        return why
    if dist is None:
        d = np.zeros(0)
    else:
        if isinstance(dist, (str, bytes, dict, bool)):
            return "camera dist must be a list of numbers"
        try:
            d = np.asarray(dist, dtype=float).ravel()
        except (TypeError, ValueError):
            return "camera dist must be a list of numbers"
    if not isinstance(image_size, (list, tuple)) or len(image_size) != 2 or any(
            isinstance(v, bool) or not isinstance(v, (int, np.integer)) for v in image_size):
        return f"camera image_size must be two integers (width, height), not {image_size!r}"
    from monotracker.vision.camera_model import validate_intrinsics

    why = validate_intrinsics(Ka, d, tuple(int(v) for v in image_size))
    return f"camera: {why}" if why else None


# ---------------------------------------------------------------------- the whole plan
def plan_problems(plan, min_usable: int, anatomy: Anatomy | None, limits: PlanLimits = LIMITS) -> list[str]:
    """Every reason ``plan`` cannot be tracked on (empty: ready). Used by the arming gate."""
    out = []
    for f in plan.fiducials:
        why = check_fiducial(f.id, f.centre_lps_mm, f.radius_mm, f.score, f.status, limits)
        if why:
            out.append(why)
    for why in (check_fiducial_set(plan.fiducials), check_locked(plan, min_usable)):
        if why:
            out.append(why)
    if plan.fiducials_locked is not True:
        out.append("the fiducial set is not confirmed and locked")
    if not plan.path_complete:
        out.append("plan the entry and the target first")
    else:
        why = check_path(plan.entry_lps_mm, plan.target_lps_mm, plan.fiducials, anatomy, limits)
        if why:
            out.append(why)
    if plan.T_base_cam is not None:
        why = check_hand_eye(plan.T_base_cam, limits)
        if why:
            out.append(why)
    why = check_camera(plan.K, plan.dist, plan.image_size)
    if why:
        out.append(why)
    return out
