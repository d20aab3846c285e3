"""Which balls a camera at a given pose sees, and why it does not see the others.

A ball (centre ``c``, radius ``R``, sitting on skin with outward normal ``n``; LPS mm) counts as
seen from a camera at ``T_ct_cam`` when all of these hold, checked in this order (the first
failure is the reason):

1. ``"behind the camera"``: its centre is less than ``R`` + 1 mm in front of the camera;
2. ``"out of the image"``: its image (centre +- its image radius + ``IMAGE_MARGIN_PX``) is not
   wholly inside the frame (the detector refuses a cut ball);
3. ``"under the drape"``: its centre is on the covered side of the drape line;
4. ``"on the far side"``: the line of sight meets the skin at more than ``MAX_VIEW_ANGLE_DEG``
   from the normal (the head's own horizon);
5. ``"hidden by the head"``: a line of sight from the ball's front (its centre and four points
   of its outline) to the camera meets the skin (nose, ear, the head's curve);
6. ``"behind the <robot part>"``: the line of sight passes through a keep-out volume.

A seen ball also gets how much of its background is skin (:func:`skin_around`): a ball on the
head's outline in the image, or beside the drape, is still seen but is often lost by the
detector, so the planner places no new ball there (:data:`PLACE_MIN_SKIN_AROUND`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monotracker.geometry import apply_transform, invert_transform

#: lines of sight steeper than this to the skin normal are the head's horizon (deg)
MAX_VIEW_ANGLE_DEG = 85.0
#: the planner places a NEW ball only where the planned camera sees it at most this far from its
#: skin normal (deg). Beyond it the ball's lower outline runs along its own contact shadow and the
#: skin: on our simulator's frames balls seen at 63-84 deg carried a centre bias of 0.10-0.14 px
#: against 0.01-0.06 px nearer the normal, a bias common to the frames that the first-order model
#: does not have, and detection on physically rendered frames is verified only up to ~65 deg.
#: Balls already on the head still count up to :data:`MAX_VIEW_ANGLE_DEG`, as the tracker uses them.
PLACE_MAX_VIEW_ANGLE_DEG = 60.0
#: the ring around a ball whose background :func:`skin_around` looks at: this many ball radii
#: from its centre, across its line of sight (the edge fit reads a ball's edge against the
#: background just outside it; a ring of 2 radii is about where the fit's rays end on the frames
#: of issue 28), sampled by :data:`SURROUND_RAYS` lines of sight
SURROUND_RING_RADII = 2.0
SURROUND_RAYS = 16
#: the planner places a NEW ball only where at least this share of that ring is exposed skin
#: (:func:`skin_around`). A ball on the head's outline in the camera's view, or beside the drape,
#: has a background of two kinds on its edge, and the detector loses such balls: on the rendered
#: planner-placed tuning frames of issue 28 (clean, frame 1, 237 whole balls; docs/planning.md
#: "Skin around a ball") balls with skin all round were found in 73 %, the others in about a
#: third (those on the outline 23 %), and 45-60 deg from the normal, 76 % against 48 %. The
#: planner's own layouts had put 8 of 12 and 6 of 9 balls there; with this rule its layouts were
#: trusted within 1 mm at frame 8 in 55-62 % of held-out scenes instead of 15-22 %.
PLACE_MIN_SKIN_AROUND = 0.9
#: a ball's image must stay this far inside the frame (px)
IMAGE_MARGIN_PX = 4.0
#: rays start this far in front of the ball's surface (mm): clear of the skin the CT's mesh
#: wraps around an existing ball
RAY_START_MM = 2.5

REASONS = ("behind the camera", "out of the image", "under the drape", "on the far side", "hidden by the head")


@dataclass(frozen=True)
class Visibility:
    """``seen`` (n,) bool and ``why`` n strings ('' where seen) for one camera pose;
    ``view_angle_deg`` (n,) the angle between each ball's skin normal and its line of sight to
    the camera (deg; 0 = seen head-on, 90 = grazing); ``skin_around`` (n,) the share (0-1) of the
    ring around each seen ball whose background in the camera's view is exposed skin
    (:func:`skin_around`; NaN where the ball is not seen)."""

    seen: np.ndarray
    why: tuple
    view_angle_deg: np.ndarray
    skin_around: np.ndarray | None = None

    @property
    def count(self) -> int:
        return int(np.sum(self.seen))

    @property
    def short_of_skin(self) -> np.ndarray:
        """(n,) bool: seen balls with less than :data:`PLACE_MIN_SKIN_AROUND` of their ring on
        exposed skin (on the head's outline in this view, or beside the drape), where the
        detector loses balls: the planner places no new ball there and names the CT's own
        fiducials that are. All False when ``skin_around`` was not computed."""
        if self.skin_around is None:
            return np.zeros(len(self.seen), bool)
        return self.seen & (np.nan_to_num(self.skin_around, nan=1.0) < PLACE_MIN_SKIN_AROUND)


def image_radius_px(X_cam: np.ndarray, radius_mm: float, focal_px: float) -> np.ndarray:
    """(n,) approximate image radius (px) of balls whose centres are ``X_cam`` (n, 3) mm."""
    d2 = np.sum(np.asarray(X_cam, float) ** 2, axis=1)
    return focal_px * radius_mm / np.sqrt(np.maximum(d2 - radius_mm**2, 1e-9))


def visibility(problem, T_ct_cam: np.ndarray, centres: np.ndarray, normals: np.ndarray) -> Visibility:
    """The :class:`Visibility` of balls ``centres`` (n, 3) with skin normals ``normals`` (n, 3)
    (LPS mm) from a camera at ``T_ct_cam`` (4x4, camera -> CT mm), for ``problem``
    (:class:`~.problem.PlanningProblem`: head, camera model, drape, keep-outs)."""
    C = np.asarray(centres, float).reshape(-1, 3)
    N = np.asarray(normals, float).reshape(-1, 3)
    n = len(C)
    why = np.full(n, "", dtype=object)
    cam, R = problem.camera, problem.radius_mm
    eye = np.asarray(T_ct_cam, float)[:3, 3]
    Xc = apply_transform(invert_transform(np.asarray(T_ct_cam, float)), C)

    def mark(mask, reason):
        why[mask & (why == "")] = reason

    mark(Xc[:, 2] <= R + 1.0, "behind the camera")
    front = why == ""
    if np.any(front):
        px = np.full((n, 2), np.nan)
        px[front] = cam.project(Xc[front])
        rp = image_radius_px(Xc, R, float(cam.K[0, 0])) + IMAGE_MARGIN_PX
        w, h = cam.image_size
        inside = (px[:, 0] - rp >= 0) & (px[:, 0] + rp <= w - 1) & (px[:, 1] - rp >= 0) & (px[:, 1] + rp <= h - 1)
        mark(front & ~inside, "out of the image")
    if problem.drape is not None:
        mark(problem.drape.covers(C), "under the drape")
    v = eye - C
    dist = np.linalg.norm(v, axis=1)
    v = v / np.maximum(dist, 1e-9)[:, None]
    cos_view = np.einsum("ij,ij->i", v, N)
    mark(cos_view < np.cos(np.radians(MAX_VIEW_ANGLE_DEG)), "on the far side")
    test = np.flatnonzero(why == "")
    if len(test):
        mark_idx = test[_head_blocks(problem.head, C[test], v[test], eye, R)]
        why[mark_idx] = "hidden by the head"
    for k in problem.space.keep_out:
        mark(k.crosses(C, np.repeat(eye[None], n, axis=0)), f"behind the {k.name}")
    seen = why == ""
    angle = np.degrees(np.arccos(np.clip(cos_view, -1.0, 1.0)))
    around = np.full(n, np.nan)
    if np.any(seen):
        around[seen] = skin_around(problem, eye, C[seen])
    return Visibility(seen, tuple(str(s) for s in why), angle, around)


def skin_around(problem, eye: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(n,) for balls ``centres`` (n, 3) seen from a camera at ``eye`` (3,) (LPS mm): the share of
    :data:`SURROUND_RAYS` lines of sight through the ring :data:`SURROUND_RING_RADII` ball radii
    from each centre (across its line of sight) that first meet the head's skin on the exposed
    side of the drape line (``problem.drape``; none: any skin). The rest pass beside the head
    (the ball is on its outline in the image) or meet covered skin (the drape lies beside the
    ball): what the detector sees around such a ball is not skin."""
    C = np.asarray(centres, float).reshape(-1, 3)
    m = len(C)
    if m == 0:
        return np.zeros(0)
    eye = np.asarray(eye, float).reshape(3)
    v = C - eye
    a, b = _across(v / np.maximum(np.linalg.norm(v, axis=1), 1e-9)[:, None])
    th = np.linspace(0.0, 2.0 * np.pi, SURROUND_RAYS, endpoint=False)
    rho = SURROUND_RING_RADII * float(problem.radius_mm)
    ring = C[None] + rho * (np.cos(th)[:, None, None] * a[None] + np.sin(th)[:, None, None] * b[None])   # (k, m, 3)
    P = ring.reshape(-1, 3)
    hits = problem.head.first_hits(np.repeat(eye[None], len(P), axis=0), P - eye)
    skin = np.all(np.isfinite(hits), axis=1)
    if problem.drape is not None and np.any(skin):
        skin[skin] = ~problem.drape.covers(hits[skin])
    return skin.reshape(SURROUND_RAYS, m).mean(axis=0)


def _across(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two (m, 3) unit vectors across each unit direction ``v`` (m, 3), orthogonal to it and to
    each other (a ring around a ball, across its line of sight)."""
    a = np.cross(v, np.array([0.0, 0.0, 1.0]))
    bad = np.linalg.norm(a, axis=1) < 1e-6
    a[bad] = np.cross(v[bad], np.array([1.0, 0.0, 0.0]))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    return a, np.cross(v, a)


def _head_blocks(head, C: np.ndarray, v: np.ndarray, eye: np.ndarray, R: float) -> np.ndarray:
    """(m,) bool: a ray from the front of each ball (its centre's and four outline points')
    towards the camera meets the skin."""
    m = len(C)
    a, b = _across(v)
    rim = 0.8 * R
    lift = np.sqrt(R * R - rim * rim) + RAY_START_MM
    starts = [C + (R + RAY_START_MM) * v]
    for s, u in ((1, a), (-1, a), (1, b), (-1, b)):
        starts.append(C + s * rim * u + lift * v)
    O = np.vstack(starts)
    hit = head.blocked(O, np.repeat(eye[None], len(O), axis=0))
    return hit.reshape(5, m).any(axis=0)
