"""The shading check (issue 28, :mod:`monotracker.vision.shading_check`).

A frame whose balls sit beside contact shadows has two readings of each ball's centre: the edge
fit's, and that moved by the ball's shading shift. Where the pose the second readings give lies
far from the frame's pose at the target, the frame is not trusted. The truth here is computed by
this file, not by the tracker's linearisation: the second readings' pose is refitted by the
registration (``refine_pose``) to the moved centres, and its distance at the 80 mm-deep target
measured; the scene's balls are projected with ``sim.scenes``' OpenCV projection.
"""

import re

import cv2
import numpy as np
import pytest
from layout_fields import worst_layout_field

from monotracker.registration.pnp import refine_pose
from monotracker.sim.scenes import _to_pixels, ellipse_centre_normalised, make_scene
from monotracker.vision import lens_range, shading_check
from monotracker.vision.camera_model import CameraModel
from monotracker.vision.detection import Detection, ImageFiducial
from monotracker.vision.frames import Frame
from monotracker.vision.pose_tracker import PoseTracker, TrackerConfig

BLANK = np.zeros((720, 1280, 3), np.uint8)


@pytest.fixture(scope="module")
def scene():
    s = make_scene(np.random.default_rng(11), noise_px=0.0, ellipse_bias=True, distance_mm=(450.0, 500.0))
    Xc = s.fiducials_ct @ s.T_cam_ct[:3, :3].T + s.T_cam_ct[:3, 3]
    px = _to_pixels(ellipse_centre_normalised(Xc, s.radius_mm), s.K, s.dist)
    minor = s.K[0, 0] * s.radius_mm / np.sqrt(Xc[:, 2] ** 2 - s.radius_mm**2)
    return s, s.targets_ct[8], px, minor                     # the target 80 mm deep


def _target_of(s, px, target) -> np.ndarray:
    """The target (camera frame, mm) under the pose refitted to image centres ``px``."""
    xn = cv2.undistortPoints(px.reshape(-1, 1, 2), s.K, s.dist).reshape(-1, 2)
    T = refine_pose(s.T_cam_ct, s.fiducials_ct, xn, np.array([s.K[0, 0], s.K[1, 1]]), s.radius_mm).T
    return T[:3, :3] @ target + T[:3, 3]


def _gradient_shifts(s, px, target, move_mm) -> np.ndarray:
    """Per-ball shifts (k, 2) px that change linearly across the layout, the field that moves the
    refitted target most (:func:`layout_fields.worst_layout_field`), scaled so that the second
    readings' pose lies ``move_mm`` from the first at the target (refitted, bisected on the scale)."""
    field = worst_layout_field(px, lambda shifts: _target_of(s, px + shifts, target))
    return _scale_for_move(s, px, target, field, move_mm) * field


def _scale_for_move(s, px, target, field, move_mm) -> float:
    """The scale of the per-ball shifts ``field`` (k, 2) px at which the pose refitted to
    ``px`` + scale x ``field`` lies ``move_mm`` from the first at the target (bisected)."""
    t0 = _target_of(s, px, target)

    def move(scale):
        return np.linalg.norm(_target_of(s, px + scale * field, target) - t0)

    lo, hi = 0.0, 1.0
    while move(hi) < move_mm:
        hi *= 2.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if move(mid) < move_mm else (lo, mid)
    return 0.5 * (lo + hi)


class _ShadedBalls:
    """Hands over the balls at their true centres (plus 0.03 px noise) as a sharp frame's edge
    fit would (edge spread 0.08 px), each with a shading shift and a contact shadow report."""

    def __init__(self, px, minor, shifts, shadow_rays, shadow_side, bands=False):
        self.px, self.minor, self.shifts = px, minor, shifts
        self.rays = np.broadcast_to(np.asarray(shadow_rays), (len(px),))
        self.side = shadow_side                  # -1: the shadow opposite the shift (unlit side)
        self.bands = np.broadcast_to(np.asarray(bands, bool), (len(px),))   # a band beside the unlit limb
        self.rng = np.random.default_rng(5)

    def detect(self, image, hint=None) -> Detection:
        fids = []
        for p, b, v, n, band in zip(self.px, self.minor, self.shifts, self.rays, self.bands):
            unit = np.asarray(v, float) / max(float(np.linalg.norm(v)), 1e-12)
            feats = {"edge_rms_px": 0.08, "shading_shift_vec_px": (float(v[0]), float(v[1])),
                     "edge_shadow_rays": int(n), "edge_shadow_dir": tuple(0.8 * self.side * unit) if n else (0.0, 0.0),
                     "edge_minor_px": float(b), "skin_band": bool(band)}
            fids.append(ImageFiducial(np.array(p, float) + self.rng.normal(scale=0.03, size=2), (float(b), float(b)),
                                      0.0, 1.0, float(np.pi * b * b), features=feats))
        return Detection(fids, [], 0.0, "shaded-double")


def _stream(s, target, det, config=None, frames=6):
    camera = CameraModel(s.K, s.dist, (1280, 720))
    trk = PoseTracker(s.fiducials_ct, camera, detector=det, radius_mm=s.radius_mm, target_ct=target,
                      config=config or TrackerConfig())
    return [trk.process(Frame(BLANK, k / 30.0, k)) for k in range(frames)]


def test_a_pose_the_second_readings_move_is_not_trusted(scene):
    """The second readings' pose lies 0.7 mm from the frame's at the target (refitted here): with
    the factor 2 the predicted error is at least 1.4 mm x 0.9 (the tracker's linearisation) and no
    frame is trusted; without the check the same frames are trusted (the balls themselves are
    sharp and right)."""
    s, target, px, minor = scene
    shifts = _gradient_shifts(s, px, target, 0.7)
    off = _stream(s, target, _ShadedBalls(px, minor, shifts, 6, -1), TrackerConfig(shading_check_factor=0.0))
    assert all(e.ok for e in off[2:]), [e.reason for e in off]
    now = _stream(s, target, _ShadedBalls(px, minor, shifts, 6, -1))
    assert not any(e.ok for e in now), [e.predicted_tre_mm for e in now]
    assert all(e.code == "tre_limit" for e in now[2:]), [e.reason for e in now]
    # the reason says what the check saw: the move at the target, within 10 % of the refitted one
    said = [re.search(r"the shading-corrected centres move the target ([0-9.]+) mm", e.reason) for e in now[2:]]
    assert all(m and abs(float(m.group(1)) - 0.7) <= 0.07 for m in said), [e.reason for e in now]
    assert all(e.predicted_tre_mm >= 0.9 * 2 * 0.7 for e in now[2:]), [e.predicted_tre_mm for e in now]


@pytest.mark.parametrize("rays, side", [(2, 1), (1, -1)])
def test_two_rays_anywhere_or_one_on_the_unlit_side_is_a_shadow(scene, rays, side):
    """A ball counts as shadowed with 2 or more rays left out wherever they lie, or 1 on its
    unlit side: the same 0.7 mm disagreement is then not trusted."""
    s, target, px, minor = scene
    shifts = _gradient_shifts(s, px, target, 0.7)
    now = _stream(s, target, _ShadedBalls(px, minor, shifts, rays, side))
    assert not any(e.ok for e in now), [e.predicted_tre_mm for e in now]


def test_a_small_disagreement_changes_nothing(scene):
    """Second readings whose pose lies 0.05 mm away: twice that is below what the frame's own
    cover predicts, and the prediction is the one without the check, to rounding."""
    s, target, px, minor = scene
    shifts = _gradient_shifts(s, px, target, 0.05)
    now = _stream(s, target, _ShadedBalls(px, minor, shifts, 6, -1))
    off = _stream(s, target, _ShadedBalls(px, minor, shifts, 6, -1), TrackerConfig(shading_check_factor=0.0))
    assert all(e.ok for e in now[2:]), [e.reason for e in now]
    np.testing.assert_allclose([e.predicted_tre_mm for e in now], [e.predicted_tre_mm for e in off], rtol=1e-9)


@pytest.mark.parametrize("case", ["no shadow", "one ray on the lit side", "too few shadowed"])
def test_without_contact_shadows_the_check_does_not_apply(scene, case):
    """The shading shift is also seen where nothing pushes the edge (a shaded ball with no contact
    shadow: our simulator's): there the same disagreement costs nothing. No shadow rays; a single
    ray left out on the lit side (the shift's own direction: what blur or a drape's edge gives
    now and then); or shadows beside fewer than half the balls: trusted as without the check."""
    s, target, px, minor = scene
    shifts = _gradient_shifts(s, px, target, 0.7)
    k = len(px)
    rays, side = {"no shadow": (0, -1), "one ray on the lit side": (1, 1),
                  "too few shadowed": ((np.arange(k) < (k - 1) // 2) * 6, -1)}[case]
    now = _stream(s, target, _ShadedBalls(px, minor, shifts, rays, side))
    off = _stream(s, target, _ShadedBalls(px, minor, shifts, rays, side), TrackerConfig(shading_check_factor=0.0))
    assert all(e.ok for e in now[2:]), [e.reason for e in now]
    np.testing.assert_allclose([e.predicted_tre_mm for e in now], [e.predicted_tre_mm for e in off], rtol=1e-9)


@pytest.mark.parametrize("case, checked", [("bands beside all", True), ("bands beside half", True),
                                           ("bands and rays beside a third each", False)])
def test_a_band_of_shadow_beside_the_limb_is_shadow_evidence(scene, case, checked):
    """A ball whose skin band reads as a band of contact shadow (``features["skin_band"]``,
    :mod:`monotracker.vision.skin_band`) counts as shadowed though its edge fit left no ray out:
    with bands beside half the balls or more the 0.7 mm disagreement is not trusted. The share is
    the larger of the two readings', not their union: bands beside one third of the balls and
    shadow rays beside another third leave the frames judged as without the check."""
    s, target, px, minor = scene
    shifts = _gradient_shifts(s, px, target, 0.7)
    k = len(px)
    idx = np.arange(k)
    rays, bands = {"bands beside all": (0, True), "bands beside half": (0, idx < (k + 1) // 2),
                   "bands and rays beside a third each": ((idx >= k - k // 3) * 6, idx < k // 3)}[case]
    if case.startswith("bands and rays"):
        assert (k // 3) / k < 0.5 and 2 * (k // 3) / k >= 0.5     # the union would reach half
    now = _stream(s, target, _ShadedBalls(px, minor, shifts, rays, -1, bands))
    if checked:
        assert not any(e.ok for e in now), [e.predicted_tre_mm for e in now]
    else:
        off = _stream(s, target, _ShadedBalls(px, minor, shifts, rays, -1, bands), TrackerConfig(shading_check_factor=0.0))
        assert all(e.ok for e in now[2:]), [e.reason for e in now]
        np.testing.assert_allclose([e.predicted_tre_mm for e in now], [e.predicted_tre_mm for e in off], rtol=1e-9)


def test_a_banded_balls_reading_is_at_least_the_band_floor(scene):
    """``TrackerConfig.shading_check_band_floor_px`` (opt-in): where the check applies, a ball with
    a band of shadow beside its unlit limb is read at least that far towards its lit side. Shifts
    whose pose moves the target 0.05 mm are trusted; with every ball banded and the floor set to
    the length at which readings of that length along the same directions move the refitted target
    0.7 mm (bisected here), no frame is trusted and the reason says ~0.7 mm; unbanded balls are read
    as without the floor."""
    s, target, px, minor = scene
    shifts = _gradient_shifts(s, px, target, 0.05)
    units = shifts / np.linalg.norm(shifts, axis=1)[:, None]
    floor = _scale_for_move(s, px, target, units, 0.7)
    assert floor > np.linalg.norm(shifts, axis=1).max()
    plain = _stream(s, target, _ShadedBalls(px, minor, shifts, 0, -1, True))
    assert all(e.ok for e in plain[2:]), [e.reason for e in plain]
    floored = _stream(s, target, _ShadedBalls(px, minor, shifts, 0, -1, True),
                      TrackerConfig(shading_check_band_floor_px=floor))
    assert not any(e.ok for e in floored), [e.predicted_tre_mm for e in floored]
    said = [re.search(r"the shading-corrected centres move the target ([0-9.]+) mm", e.reason) for e in floored[2:]]
    assert all(m and abs(float(m.group(1)) - 0.7) <= 0.07 for m in said), [e.reason for e in floored]
    unbanded = _stream(s, target, _ShadedBalls(px, minor, shifts, 6, -1, False),
                       TrackerConfig(shading_check_band_floor_px=floor))
    assert all(e.ok for e in unbanded[2:]), [e.reason for e in unbanded]


def test_the_band_floor_by_hand():
    feats = [{"shading_shift_vec_px": (0.1, 0.0), "skin_band": True},
             {"shading_shift_vec_px": (0.0, -0.6), "skin_band": True},
             {"shading_shift_vec_px": (0.0, 0.1), "skin_band": False},
             {"shading_shift_vec_px": (0.0, 0.0), "skin_band": True}]
    np.testing.assert_allclose(shading_check.second_readings(feats, band_min_px=0.4),
                               [[0.4, 0.0], [0.0, -0.6], [0.0, 0.1], [0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(shading_check.second_readings(feats, min_px=0.2, band_min_px=0.4),
                               [[0.4, 0.0], [0.0, -0.6], [0.0, 0.2], [0.0, 0.0]], atol=1e-12)


@pytest.mark.parametrize("floor", [-0.1, float("nan")])
def test_a_band_floor_that_is_not_a_length_is_refused_at_construction(floor):
    with pytest.raises(ValueError, match="shading_check_band_floor_px"):
        TrackerConfig(shading_check_band_floor_px=floor)


@pytest.mark.parametrize("over_radius_px, checked", [(None, False), (0.2, True), (-0.2, False)])
def test_small_balls_are_checked_without_shadow_evidence_where_asked(scene, over_radius_px, checked):
    """``TrackerConfig.shading_check_small_radius_px`` (opt-in): balls whose median fitted radius
    (``edge_minor_px``) is under it are checked though none shows a contact shadow (a small ball's
    few rays rarely do): the 0.7 mm disagreement is then not trusted. Off (0, the default: None
    here), or a limit 0.2 px under the balls' own radius, the frames are judged as without the
    check; 0.2 px over it, they are checked."""
    s, target, px, minor = scene
    limit = 0.0 if over_radius_px is None else float(np.median(minor)) + over_radius_px
    shifts = _gradient_shifts(s, px, target, 0.7)
    now = _stream(s, target, _ShadedBalls(px, minor, shifts, 0, -1), TrackerConfig(shading_check_small_radius_px=limit))
    if checked:
        assert not any(e.ok for e in now), [e.predicted_tre_mm for e in now]
        assert all("the shading-corrected centres move the target" in e.reason for e in now[2:]), [e.reason for e in now]
    else:
        assert all(e.ok for e in now[2:]), [e.reason for e in now]


def _unseen_push(s, px, target, move_mm) -> tuple[np.ndarray, float]:
    """Per-ball directions (k, 2; unit) of the field that moves the refitted target most, and the
    push m (px) along them, the same length on every ball, whose refitted pose lies ``move_mm``
    from the first at the target (bisected here on m)."""
    field = worst_layout_field(px, lambda shifts: _target_of(s, px + shifts, target))
    unit = field / np.linalg.norm(field, axis=1, keepdims=True)
    return unit, _scale_for_move(s, px, target, unit, move_mm)


@pytest.mark.parametrize("case", ["off", "no shadow seen", "shadows seen", "a third seen, a quarter asked",
                                  "a third seen, half asked"])
def test_a_push_not_seen_is_taken_as_at_least_the_floor(scene, case):
    """``TrackerConfig.shading_check_unseen_push_px`` (opt-in): where the shadows seen do not make
    the check apply, each shaded ball's second reading lies at least the floor towards its lit
    side. The balls' shading shifts here are 0.01 px long, along the field that moves the target
    most; the floor is the push along those directions whose refitted pose lies 0.7 mm away at
    the target. With no shadow seen, or shadows beside a third of the balls where
    ``shading_check_push_min_share`` asks a quarter, the frames are then not trusted and the
    reason's move is that refit's (within 10 %); with the floor off, with shadows seen beside
    every ball (the check reads the shifts themselves, 0.01 px), or beside a third where
    ``shading_check_push_min_share`` asks half (0.49), they are judged as without the check."""
    s, target, px, minor = scene
    unit, floor = _unseen_push(s, px, target, 0.7)
    shifts = 0.01 * unit
    k = len(px)
    a_third = (np.arange(k) < int(np.ceil(k / 3))) * 6
    rays = {"shadows seen": 6, "a third seen, a quarter asked": a_third, "a third seen, half asked": a_third}.get(case, 0)
    min_share = {"a third seen, a quarter asked": 0.25, "a third seen, half asked": 0.49}.get(case, 0.0)
    cfg = TrackerConfig(shading_check_unseen_push_px=0.0 if case == "off" else floor,
                        shading_check_push_min_share=min_share)
    now = _stream(s, target, _ShadedBalls(px, minor, shifts, rays, -1), cfg)
    if case in ("no shadow seen", "a third seen, a quarter asked"):
        assert not any(e.ok for e in now), [e.predicted_tre_mm for e in now]
        said = [re.search(r"the shading-corrected centres move the target ([0-9.]+) mm", e.reason) for e in now[2:]]
        assert all(m and abs(float(m.group(1)) - 0.7) <= 0.07 for m in said), [e.reason for e in now]
    else:
        off = _stream(s, target, _ShadedBalls(px, minor, shifts, rays, -1), TrackerConfig(shading_check_factor=0.0))
        assert all(e.ok for e in now[2:]), [e.reason for e in now]
        np.testing.assert_allclose([e.predicted_tre_mm for e in now], [e.predicted_tre_mm for e in off], rtol=1e-6)


def test_the_push_floor_keeps_a_ball_without_shading_at_its_edge_centre():
    """:func:`shading_check.second_readings` with ``min_px``: a shift shorter than the floor is
    lengthened to it along its own direction, a longer one is kept, a ball with no shift (no
    visible shading) reads 0."""
    feats = [{"shading_shift_vec_px": (0.06, -0.08)}, {"shading_shift_vec_px": (0.0, 0.5)},
             {"shading_shift_vec_px": (0.0, 0.0)}]
    got = shading_check.second_readings(feats, min_px=0.3)
    np.testing.assert_allclose(got, [[0.18, -0.24], [0.0, 0.5], [0.0, 0.0]], atol=1e-12)


def test_the_raised_covariance_predicts_factor_times_the_move_at_the_target(scene):
    """:func:`shading_check.raised_covariance` against finite differences of this file's own
    pose arithmetic: the target's move under a pose change d and the RMS a covariance predicts
    there; a small covariance is raised to exactly factor x the move, a large one kept."""
    s, target, _px, _minor = scene
    T = s.T_cam_ct

    def moved_target(d):          # the pose parameters' convention: R -> exp(d_rot) R, t -> t + d_t
        R = cv2.Rodrigues(np.asarray(d[:3], float))[0]
        return R @ T[:3, :3] @ target + T[:3, 3] + d[3:]

    t0 = moved_target(np.zeros(6))
    G = np.array([(moved_target(e * 1e-7) - t0) / 1e-7 for e in np.eye(6)]).T     # (3, 6) mm per unit

    def rms(cov):
        return float(np.sqrt(np.trace(G @ cov @ G.T)))

    d = np.array([2e-4, -1e-4, 3e-4, 0.1, -0.2, 0.05])
    move = float(np.linalg.norm(G @ d))
    small = np.diag([1e-9] * 3 + [1e-4] * 3)
    raised = shading_check.raised_covariance(small, d, T, target, 2.0)
    assert rms(raised) == pytest.approx(2.0 * move, rel=1e-5)
    large = np.diag([1e-5] * 3 + [1.0] * 3)
    assert rms(large) > 2.0 * move
    np.testing.assert_array_equal(shading_check.raised_covariance(large, d, T, target, 2.0), large)


class _FlickeringShadows(_ShadedBalls):
    """:class:`_ShadedBalls` whose contact shadows the edge fit reports in some frames and not in
    others (``shadowed[k]``: frame k reports 6 rays beside every ball, else beside fewer than half
    of them), the head moving ``drift_px`` per frame across the image (0: still)."""

    def __init__(self, px, minor, shifts, shadowed, drift_px=0.0):
        super().__init__(px, minor, shifts, 6, -1)
        self.shadowed, self.drift, self.k = list(shadowed), float(drift_px), 0
        k = len(px)
        self.few = (np.arange(k) < (k - 1) // 2) * 6

    def detect(self, image, hint=None) -> Detection:
        self.rays = np.full(len(self.px), 6) if self.shadowed[self.k] else self.few
        base = self.px
        self.px = base + self.drift * self.k * np.array([1.0, 0.0])
        try:
            return super().detect(image, hint)
        finally:
            self.px = base
            self.k += 1


def test_a_still_heads_contact_shadows_count_in_the_frames_whose_edge_fits_miss_them(scene):
    """A contact shadow does not leave a still head between two frames; the edge fit's shadow
    test does now and then. Frames 0-1 show shadows beside every ball, frames 2-12 beside fewer
    than half: the check goes on applying while a frame of the last 7 (the ball memory's age)
    showed them (frames 2-8: not trusted), then no longer (frames 9-12: trusted). Each frame on
    its own shadows (``shading_check_still_frames`` False, the default before) or without the
    ball memory (``remember_frames`` 0), frames 2-12 are trusted: what the rendered 12-ball
    plans' trusted frames 1-2 mm off were."""
    s, target, px, minor = scene
    shifts = _gradient_shifts(s, px, target, 0.7)
    shadowed = [True, True] + [False] * 11
    now = _stream(s, target, _FlickeringShadows(px, minor, shifts, shadowed), frames=13)
    assert not any(e.ok for e in now[:9]), [e.predicted_tre_mm for e in now]
    assert all(e.ok for e in now[9:]), [e.reason for e in now]
    assert all(re.search(r"the shading-corrected centres move the target", e.reason) for e in now[2:9]), \
        [e.reason for e in now]
    for config in (TrackerConfig(shading_check_still_frames=False), TrackerConfig(remember_frames=0)):
        alone = _stream(s, target, _FlickeringShadows(px, minor, shifts, shadowed), config, frames=13)
        assert not any(e.ok for e in alone[:2])
        assert all(e.ok for e in alone[2:]), [e.reason for e in alone]


def test_a_moving_heads_frames_are_judged_on_their_own_shadows(scene):
    """The same frames from a head moving 1 px a frame across the image: no past frame passes
    the memory's stillness test, so a frame without shadows beside half its balls is judged on
    its own, as before (trusted from frame 2 on)."""
    s, target, px, minor = scene
    shifts = _gradient_shifts(s, px, target, 0.7)
    now = _stream(s, target, _FlickeringShadows(px, minor, shifts, [True, True] + [False] * 6, drift_px=1.0),
                  frames=8)
    assert not any(e.ok for e in now[:2])
    assert all(e.ok for e in now[2:]), [e.reason for e in now]


def _outline_minor_px(s) -> np.ndarray:
    """Each ball's outline minor semi-axis in the distorted image (px): the sphere's tangent cone
    from the camera, 720 rays projected by OpenCV with the scene's distortion, the ellipse
    OpenCV fits to them."""
    Xc = s.fiducials_ct @ s.T_cam_ct[:3, :3].T + s.T_cam_ct[:3, 3]
    th = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
    out = []
    for c in Xc:
        u = c / np.linalg.norm(c)
        a = np.arcsin(s.radius_mm / np.linalg.norm(c))
        e1 = np.cross(u, [0.0, 0.0, 1.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        rays = np.cos(a) * u + np.sin(a) * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
        p = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), s.K, s.dist)[0].reshape(-1, 2)
        out.append(0.5 * min(cv2.fitEllipse(p.astype(np.float32))[1]))
    return np.array(out)


class _SizedShadedBalls(_ShadedBalls):
    """:class:`_ShadedBalls` whose edge fits also report their outline's minor semi-axis: the
    sphere's own in the distorted image (:func:`_outline_minor_px` of ``s``) plus ``excess`` px
    per ball."""

    def __init__(self, s, px, minor, shifts, excess, shadow_rays=6, shadow_side=-1):
        super().__init__(px, minor, shifts, shadow_rays, shadow_side)
        self.outline = _outline_minor_px(s) + np.broadcast_to(np.asarray(excess, float), (len(px),))

    def detect(self, image, hint=None) -> Detection:
        d = super().detect(image, hint)
        for f, b in zip(d.fiducials, self.outline):
            f.features["edge_minor_px"] = float(b)
        return d


def _field_as_direction_and_size(field):
    """The shading shifts (each 0.25 px long, pointing along ``field``) and outline excesses
    (``field``'s lengths) whose excess readings are ``field`` itself."""
    length = np.linalg.norm(field, axis=1)
    return 0.25 * field / length[:, None], length


def test_the_second_readings_follow_the_outlines_size_excess():
    """:func:`shading_check.second_readings` by hand: towards the lit side (the shift's direction)
    by the excess, never against it (a negative excess reads as none), at most the cap; the shift
    itself without an excess; no direction, no move."""
    feats = [{"shading_shift_vec_px": (0.3, 0.4)}, {"shading_shift_vec_px": (-0.2, 0.0)},
             {"shading_shift_vec_px": (0.0, 0.1)}, {"shading_shift_vec_px": (0.0, 0.0)}]
    got = shading_check.second_readings(feats, np.array([0.5, -0.3, 2.5, 0.4]))
    np.testing.assert_allclose(got, [[0.3, 0.4], [0.0, 0.0], [0.0, shading_check.EXCESS_CAP_PX], [0.0, 0.0]],
                               atol=1e-12)
    np.testing.assert_array_equal(shading_check.second_readings(feats), [[0.3, 0.4], [-0.2, 0.0], [0.0, 0.1],
                                                                         [0.0, 0.0]])


#: the opt-in reading of the second centres from the outlines' size excess
EXCESS = TrackerConfig(shading_check_reading="excess")


def test_outlines_pushed_out_by_the_shading_are_not_trusted(scene):
    """Read from the outlines (``shading_check_reading="excess"``): shading shifts of 0.25 px, each
    ball's outline too large by the length of a layout field whose second readings move the
    refitted target 0.7 mm: not trusted, and the reason says a move within 10 % of 0.7 mm (the
    excess read, not the shift's 0.25 px)."""
    s, target, px, minor = scene
    shifts, excess = _field_as_direction_and_size(_gradient_shifts(s, px, target, 0.7))
    now = _stream(s, target, _SizedShadedBalls(s, px, minor, shifts, excess), EXCESS)
    assert not any(e.ok for e in now), [e.predicted_tre_mm for e in now]
    said = [re.search(r"the shading-corrected centres move the target ([0-9.]+) mm", e.reason) for e in now[2:]]
    assert all(m and abs(float(m.group(1)) - 0.7) <= 0.07 for m in said), [e.reason for e in now]


@pytest.mark.parametrize("excess", [0.0, -0.3])
def test_outlines_of_the_spheres_size_are_trusted_whatever_the_shading_model_says(scene, excess):
    """Read from the outlines: the shading model's shifts give the 0.7 mm field, but every outline
    is the sphere's own size (or smaller): no push, the frames are trusted as without the check;
    read from the shift (the default) the same frames are refused."""
    s, target, px, minor = scene
    shifts = _gradient_shifts(s, px, target, 0.7)
    now = _stream(s, target, _SizedShadedBalls(s, px, minor, shifts, excess), EXCESS)
    off = _stream(s, target, _SizedShadedBalls(s, px, minor, shifts, excess), TrackerConfig(shading_check_factor=0.0))
    assert all(e.ok for e in now[2:]), [e.reason for e in now]
    np.testing.assert_allclose([e.predicted_tre_mm for e in now], [e.predicted_tre_mm for e in off], rtol=1e-6)
    default = _stream(s, target, _SizedShadedBalls(s, px, minor, shifts, excess))
    assert not any(e.ok for e in default), [e.predicted_tre_mm for e in default]


def test_an_unknown_reading_is_refused_at_construction():
    with pytest.raises(ValueError, match="shading_check_reading must be one of excess, shift"):
        TrackerConfig(shading_check_reading="size")


@pytest.mark.parametrize("push", [-0.1, float("nan")])
def test_a_push_floor_that_is_not_a_length_is_refused_at_construction(push):
    with pytest.raises(ValueError, match="shading_check_unseen_push_px must be a push in px >= 0"):
        TrackerConfig(shading_check_unseen_push_px=push)


@pytest.mark.parametrize("share", [-0.1, 1.5, float("nan")])
def test_a_push_floor_share_that_is_not_a_share_is_refused_at_construction(share):
    with pytest.raises(ValueError, match="shading_check_push_min_share must be a share of the balls from 0 to 1"):
        TrackerConfig(shading_check_push_min_share=share)


@pytest.fixture(scope="module")
def short_scene():
    """The scene's kind seen through a short lens (f = 800 px: the 4 mm balls image at 8 px from
    400 mm, under vision.lens_range's 10 px), from 450-500 mm."""
    s = make_scene(np.random.default_rng(11), noise_px=0.0, ellipse_bias=True, distance_mm=(450.0, 500.0), f=800.0)
    Xc = s.fiducials_ct @ s.T_cam_ct[:3, :3].T + s.T_cam_ct[:3, 3]
    px = _to_pixels(ellipse_centre_normalised(Xc, s.radius_mm), s.K, s.dist)
    minor = s.K[0, 0] * s.radius_mm / np.sqrt(Xc[:, 2] ** 2 - s.radius_mm**2)
    return s, s.targets_ct[8], px, minor


def test_a_short_lens_gets_the_band_floor_by_default(short_scene):
    """Through a short lens the default tracker reads each banded ball at least
    ``short_lens_band_floor_px`` (0.4 px) towards its lit side: its predicted error is at least
    twice (x 0.9, the linearisation) the refitted target move of 0.4 px readings along the balls'
    shift directions, which the lens-blind rules (0) do not reach with shifts that move it 0.05 mm."""
    s, target, px, minor = short_scene
    assert lens_range.short_lens_radius_px(CameraModel(s.K, s.dist, (1280, 720)), s.radius_mm) is not None
    shifts = _gradient_shifts(s, px, target, 0.05)
    units = shifts / np.linalg.norm(shifts, axis=1)[:, None]
    t0 = _target_of(s, px, target)
    floor_mm = float(np.linalg.norm(_target_of(s, px + TrackerConfig().short_lens_band_floor_px * units, target) - t0))
    aware = _stream(s, target, _ShadedBalls(px, minor, shifts, 0, -1, True))
    blind = _stream(s, target, _ShadedBalls(px, minor, shifts, 0, -1, True), TrackerConfig(short_lens_band_floor_px=0.0))
    assert all(e.predicted_tre_mm >= 0.9 * 2 * floor_mm for e in aware[2:]), ([e.predicted_tre_mm for e in aware], floor_mm)
    assert all(e.predicted_tre_mm < 0.9 * 2 * floor_mm for e in blind[2:]), ([e.predicted_tre_mm for e in blind], floor_mm)
    # the same lens with balls not banded: the floor does not apply
    plain = _stream(s, target, _ShadedBalls(px, minor, shifts, 6, -1, False))
    plain_blind = _stream(s, target, _ShadedBalls(px, minor, shifts, 6, -1, False), TrackerConfig(short_lens_band_floor_px=0.0))
    np.testing.assert_allclose([e.predicted_tre_mm for e in plain], [e.predicted_tre_mm for e in plain_blind], rtol=1e-12)


def test_the_generators_lens_keeps_the_rules_as_they_were(scene):
    """Through the generator's lens (f = 1100 px: 11 px balls from 400 mm) the short-lens floor
    never applies: every banded frame predicts as the lens-blind rules do, to the bit."""
    s, target, px, minor = scene
    assert lens_range.short_lens_radius_px(CameraModel(s.K, s.dist, (1280, 720)), s.radius_mm) is None
    shifts = _gradient_shifts(s, px, target, 0.3)
    now = _stream(s, target, _ShadedBalls(px, minor, shifts, 0, -1, True))
    blind = _stream(s, target, _ShadedBalls(px, minor, shifts, 0, -1, True), TrackerConfig(short_lens_band_floor_px=0.0))
    assert [e.predicted_tre_mm for e in now] == [e.predicted_tre_mm for e in blind]
    assert [e.ok for e in now] == [e.ok for e in blind]


@pytest.mark.parametrize("floor", [-0.1, float("nan")])
def test_a_short_lens_floor_that_is_not_a_length_is_refused_at_construction(floor):
    with pytest.raises(ValueError, match="short_lens_band_floor_px"):
        TrackerConfig(short_lens_band_floor_px=floor)
