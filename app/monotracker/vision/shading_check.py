"""A frame's pose must not depend on how its shaded balls' centres are read (issue 28).

What it answers: on frames where the balls sit on skin lit by an OR lamp, each ball's edge-fitted
centre is pushed towards its unlit side (the unlit limb and the contact shadow beside it read as
one dark edge, :mod:`.shading_shift`), and where the layout is spread over sloping skin (the
layout planner's own 9- and 12-ball plans) that push varies across the layout. A pose absorbs
such a field, the residuals hardly show it, and the per-frame trust model trusted poses 1-2 mm off
at an 80 mm-deep target: on the physically rendered tuning sets (30-frame still streams, default
detector) 39 of 641 trusted frames, 31 of the 479 that the session's gate passed to the arm, 33
and 27 of them on the 12-ball plan.

The check: every ball the edge fit found has a second reading of its centre: the edge centre
moved towards the ball's lit side (the direction of its shading shift,
:func:`.shading_shift.shaded_centre`: the colour blob's contour and the lit side; stored by the
detector as ``features["shading_shift_vec_px"]``) by its fitted outline's size excess over the
sphere at the frame's pose (:func:`second_readings`; ``TrackerConfig.shading_check_reading``
"excess", opt-in since 2026-12-02), or by the shading shift's own length ("shift", the default:
the linear model fitted on the rendered balls). Through the fit's linearisation the second readings give a
pose that differs from the frame's by ``d`` (6,; rotation vector rad, translation mm); the frame's
pose covariance is raised along ``d`` until its RMS error at the target is at least ``factor`` x
the target's move under ``d`` (:func:`raised_covariance`). With the TRE limit of 1 mm and factor 2
a pose is trusted only where the two readings' poses lie within 0.5 mm of each other at the
target. It is not a correction: the pose keeps the edge centres (moving them by the shift lowers
the centre error on the rendered balls but costs our simulator's right centres, see
:mod:`.shading_shift`).

It applies only to a frame whose balls show contact shadows (:func:`shadowed_share`): at least
``min_share`` of the matched balls must have had rays left out of their edge fit as a contact
shadow's (``edge_shadow_rays``, the test of :func:`.edge_fit._without_shadow_rays`): at least
:data:`MIN_SHADOW_RAYS`, or one on the ball's unlit side (the left-out rays' mean direction,
``edge_shadow_dir``, against the shading shift, which points to the lit side), or, where more
balls show it, a band of shadow beside their unlit limbs (``features["skin_band"]``,
:mod:`.skin_band`: what a small ball's few edge rays miss; since 2026-12-03). The shading shift
itself is also seen where nothing pushes the edge (our simulator's balls: shaded, no contact
shadow, edge centres right to 0.02 px), and the check there would only refuse right poses: the
shadow test flags a ray now and then there too (blur, a drape's edge), mostly one per ball and
not on the unlit side. On ``benchmarks/camera_pipeline.py``'s frames (6419 frames, 53850 balls)
at most 0.29 of a frame's balls had 2 or more such rays and at most 0.43 one on the unlit side
(any ray at all: up to 0.62, which refused 1 and 2 of its 90 OR and clutter frames); on the
rendered 12-ball plan the median frame has 0.83 of its balls with some and 0.5 with 2 or more.
The rule and its numbers: TrackerConfig.shading_check_factor, docs/vision.md "The shading check".
"""

from __future__ import annotations

import numpy as np


#: a ball's edge fit that left out this many rays as a contact shadow's has one beside it,
#: wherever they lie (fewer count only on the ball's unlit side)
MIN_SHADOW_RAYS = 2


def shadowed(features: dict) -> bool:
    """Whether a ball's detection features say a contact shadow lies beside it: the edge fit left
    out at least :data:`MIN_SHADOW_RAYS` rays as a shadow's (``edge_shadow_rays``), or at least
    one on the unlit side: their mean direction from the centre (``edge_shadow_dir``, image axes)
    against the lit side (negative dot product with ``shading_shift_vec_px``, px, which points
    towards it)."""
    n = int(features.get("edge_shadow_rays", 0))
    if n >= MIN_SHADOW_RAYS:
        return True
    shift = features.get("shading_shift_vec_px")
    if n < 1 or shift is None:
        return False
    return float(np.dot(features.get("edge_shadow_dir", (0.0, 0.0)), shift)) < 0.0


def shadowed_share(features: list) -> float:
    """Share (0-1) of the balls (their detection features) with a contact shadow beside them: the
    larger of the share whose edge rays show one (:func:`shadowed`: 2+ left-out rays anywhere, or
    1 on the unlit side) and the share with a band of shadow beside the unlit limb
    (``features["skin_band"]``, :mod:`.skin_band`: what a small ball's few rays miss); 0 for none.
    The larger, not the union: each reading is noisy on its own (our simulator's frames, which
    have no contact shadow, show up to 0.29 of their balls flagged by either), and the union of
    the two flagged half the balls of some of them (docs/vision.md "A band of shadow beside the
    limb")."""
    if not features:
        return 0.0
    return float(max(np.mean([shadowed(f) for f in features]), np.mean([bool(f.get("skin_band")) for f in features])))


def shadows_seen(features: list, still_shares: tuple, min_share: float) -> bool:
    """Whether at least ``min_share`` of a frame's matched balls (their detection features) show
    a contact shadow (:func:`shadowed_share`) in this frame or in one of ``still_shares`` (the
    shares of a still head's last frames: a contact shadow does not leave a still head). The
    shading check, its unseen-push variant and the glossy frames' cover
    (:func:`.ball_gloss.wider_cover`) all ask this."""
    return max([shadowed_share(features), *still_shares]) >= min_share


#: the most (px) a ball's second reading moves from its edge centre when read from its outline's
#: size excess (:func:`second_readings`): an unlit limb and its contact shadow read as one edge
#: push a rendered ball's outline out by well under this (tuning sets: the scenes' mean excess
#: -0.15 to +0.6 px at 5-12 px radii)
EXCESS_CAP_PX = 1.0


def second_readings(features: list, excess_px=None, cap_px: float = EXCESS_CAP_PX, min_px: float = 0.0,
                    band_min_px: float = 0.0) -> np.ndarray:
    """(k, 2) px: where each matched ball's second centre reading lies from its edge centre.

    ``excess_px`` ((k,) px or None): each ball's fitted outline minor semi-axis minus the sphere's
    at the frame's pose (the tracker's size excess). With it, the reading lies towards the ball's
    lit side (the direction of its shading shift, ``features[i]["shading_shift_vec_px"]``) by the
    excess, clipped to [0, ``cap_px``]: an outline that the unlit limb and the contact shadow
    beside it, read as one dark edge, push out on the unlit side by 2e is e px too large and its
    centre e px towards that side; an outline of the sphere's own size shows no such push, whatever
    the shading model says. Without it (a ball with no fitted size): the shading shift itself
    (:mod:`.shading_shift`'s linear model, the default reading). Measured on the
    rendered 12-ball plan's tuning frames (995 matched balls): the scenes' mean centre error along
    the shift direction is -0.44 to -0.48 px where their mean excess is +0.33 to +0.60 px, and -0.1
    to +0.1 px where it is -0.15 to +0.2, while the shift's own length is 0.12-0.39 px in both.

    ``min_px`` > 0 (the shift reading only, where no shadow evidence made the check apply:
    :func:`unseen_push_applies`): each shaded ball's reading lies at least that far (px) towards
    its lit side; a ball with no shift (no visible shading) keeps 0. ``band_min_px`` > 0 (the shift
    reading only; ``TrackerConfig.shading_check_band_floor_px``): the same floor for the balls with
    a band of shadow beside their unlit limb (``features["skin_band"]``, :mod:`.skin_band`) only."""
    shifts = np.asarray([f["shading_shift_vec_px"] for f in features], float).reshape(-1, 2)
    length = np.linalg.norm(shifts, axis=1)
    unit = shifts / np.maximum(length, 1e-12)[:, None]
    if excess_px is None:
        floor = np.full(len(shifts), float(min_px))
        if band_min_px > 0:
            banded = np.array([bool(f.get("skin_band")) for f in features], bool)
            floor = np.where(banded, np.maximum(floor, float(band_min_px)), floor)
        if np.any(floor > 0):
            return unit * np.where(length > 0, np.maximum(length, floor), 0.0)[:, None]
        return shifts
    move = np.clip(np.asarray(excess_px, float).reshape(-1), 0.0, cap_px)
    return unit * np.where(length > 0, move, 0.0)[:, None]


def readable(features: list) -> bool:
    """Whether every matched ball (its detection features) has a second reading: a shading
    shift (``shading_shift_vec_px``) and an edge centre the learned refiner did not move."""
    return bool(features) and all(f.get("shading_shift_vec_px") is not None and "edge_centre_px" not in f
                                  for f in features)


def unseen_push_applies(features: list, push_px: float, still_shares: tuple = (), min_share: float = 0.0) -> bool:
    """Whether the check applies without enough shadow evidence for :func:`applies`
    (``TrackerConfig.shading_check_unseen_push_px``, where :func:`applies` said no): ``push_px`` >
    0, every matched ball has a second reading (:func:`readable`), and at least ``min_share`` of
    the balls show a contact shadow (:func:`shadowed_share`) in this frame or in one of
    ``still_shares`` (a still head's last frames). A contact shadow not seen is not a shadow
    absent: a small ball's few edge rays rarely show it (docs/vision.md "Other lenses"), and its
    unlit limb's push, unmeasured, is taken as at least ``push_px`` towards each ball's unlit
    side."""
    if not (push_px > 0 and readable(features)):
        return False
    return min_share <= 0 or shadows_seen(features, still_shares, min_share)


def applies(features: list, min_share: float, still_shares: tuple = (), small_radius_px: float = 0.0) -> bool:
    """Whether the check applies to a frame's matched balls (their detection features): not where a
    ball has no shift (a detector without an edge fit, a centre the learned refiner moved:
    ``edge_centre_px`` set), nor where fewer than ``min_share`` of the balls are shadowed
    (:func:`shadowed_share`) in this frame and in each of ``still_shares``: the shares of the last
    frames of a still head (:meth:`.ball_memory.StillBallMemory.still_notes`). A contact shadow
    does not leave a still head between two frames; the edge fit's shadow test does, now and then
    (sensor noise tips it as it tips a ball's acceptance), and a frame whose share dipped under
    ``min_share`` alone went out unchecked: on the rendered 12-ball plans those were the trusted
    frames 1-2 mm off (docs/vision.md, "The shading check"). Where ``small_radius_px`` > 0 it
    also applies when the balls' median fitted radius (``edge_minor_px``) is under it, shadows
    seen or not: a small ball's few rays rarely show its shadow
    (``TrackerConfig.shading_check_small_radius_px``)."""
    if not readable(features):
        return False
    if small_radius_px > 0:
        radii = [f["edge_minor_px"] for f in features if f.get("edge_minor_px") is not None]
        if radii and float(np.median(radii)) < small_radius_px:
            return True
    return shadows_seen(features, still_shares, min_share)


def pose_disagreement(A: np.ndarray, features: list, excess_px=None, min_px: float = 0.0,
                      band_min_px: float = 0.0) -> np.ndarray:
    """The pose change (6,: rotation vector rad, translation mm) that moving each matched ball's
    centre to its second reading (:func:`second_readings`: by its outline's size excess
    ``excess_px`` towards its lit side, or by its shading shift where ``excess_px`` is None) gives
    through the fit's linearisation ``A`` ((6, 2k): image errors px, rows x0, y0, x1, y1, ... ->
    pose), for a frame the check :func:`applies` to (``min_px``, ``band_min_px``: :func:`second_readings`)."""
    return np.asarray(A, float) @ second_readings(features, excess_px, min_px=min_px,
                                                  band_min_px=band_min_px).reshape(-1)


def target_move_mm(d6: np.ndarray, T_cam_ct: np.ndarray, target_ct: np.ndarray) -> float:
    """How far (mm) the pose change ``d6`` (:func:`pose_disagreement`) moves ``target_ct`` (3,,
    CT mm), to first order."""
    from monotracker.registration.report import target_covariance

    return float(np.sqrt(max(np.trace(target_covariance(T_cam_ct, np.outer(d6, d6), target_ct)), 0.0)))


def raised_covariance(cov6: np.ndarray, d6: np.ndarray, T_cam_ct: np.ndarray, target_ct: np.ndarray,
                      factor: float) -> np.ndarray:
    """``cov6`` (6, 6 pose covariance) raised along ``d6`` (:func:`pose_disagreement`) so that the
    RMS error it predicts at ``target_ct`` (3,, CT mm; ``T_cam_ct`` maps CT points into the camera
    frame) is at least ``factor`` x the target's move under ``d6`` (mm): unchanged where it
    already is."""
    from monotracker.registration.report import target_covariance

    dd = np.outer(d6, d6)
    move2 = target_move_mm(d6, T_cam_ct, target_ct) ** 2
    if not move2 > 0:
        return cov6
    have2 = float(np.trace(target_covariance(T_cam_ct, cov6, target_ct)))
    need2 = factor**2 * move2
    if have2 >= need2:
        return cov6
    return cov6 + (need2 - have2) / move2 * dd
