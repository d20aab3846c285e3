"""The layout search and the planner: the exhaustive optimum on a small pool, the surgeon's rules,
the camera space, and a layout called better measuring better through the real pose stream."""

from __future__ import annotations

import itertools
import re
from dataclasses import replace

import numpy as np
import pytest
from analytic_head import PH

from monotracker.geometry import invert_transform
from monotracker.planning import plan_layout, predict, rule_of_thumb_layout, sample_candidates
from monotracker.planning.camera_poses import camera_pose
from monotracker.planning.planner import pose_data
from monotracker.planning.search import best_layout, objective
from monotracker.planning.visibility import PLACE_MAX_VIEW_ANGLE_DEG
from monotracker.registration.report import tre_mm
from monotracker.sim.scenes import _to_pixels, ellipse_centre_normalised
from monotracker.vision.frames import Frame
from monotracker.vision.point_detector import PointDetector
from monotracker.vision.pose_tracker import PoseTracker

BLANK = np.zeros((720, 1280, 3), np.uint8)


@pytest.fixture(scope="module")
def quick_plan(problem):
    """Seven balls, the camera over 8 directions, refined."""
    return plan_layout(problem, 7, n_directions=8)


def test_no_new_ball_without_skin_around_and_the_plan_names_the_ct_balls_short_of_it(problem, quick_plan):
    """Every new ball of the suggestion has skin all round it in the planned camera's view
    (``PLACE_MIN_SKIN_AROUND``), and the plan's note names exactly the CT fiducials that camera
    sees on the head's outline or beside the drape (by their CT index)."""
    from monotracker.planning.visibility import PLACE_MIN_SKIN_AROUND, skin_around

    plan = quick_plan
    v = plan.expected.visibility
    new = plan.from_existing < 0
    assert new.any() and np.all(v.skin_around[new] >= PLACE_MIN_SKIN_AROUND), v.skin_around
    ex = plan.existing_here.visibility
    ids = plan.candidates.existing[plan.candidates.existing >= 0]
    eye = plan.T_ct_cam[:3, 3]
    direct = skin_around(problem, eye, problem.existing[ids][ex.seen])
    assert np.allclose(ex.skin_around[ex.seen], direct)
    short = sorted(int(i) for i, a in zip(ids[ex.seen], direct) if a < PLACE_MIN_SKIN_AROUND)
    assert sorted(plan.outline_fiducials) == short
    assert plan.to_dict()["ct_fiducials_short_of_skin"] == list(plan.outline_fiducials)
    notes = [n for n in plan.notes if n.startswith("CT fiducial")]
    assert len(notes) == (1 if short else 0), notes
    named = {int(m) for n in notes for m in re.findall(r"#(\d+)", n)}
    assert named == set(short), (notes, short)
    assert set(plan.expected.to_dict()["skin_around"]) == {str(i) for i in np.flatnonzero(v.seen)}


def test_the_plan_names_the_ct_fiducials_by_the_ids_it_is_given(problem):
    """The app numbers its fiducials by their plan ids, not by their order: the plan's note and
    ``outline_fiducials`` use the ids it is given (each ball found by its position). The head's
    balls plus 16 more on the skin 40-64 deg from its view direction, some of which the planned
    camera sees short of skin."""
    v = PH.view_direction_lps
    u = np.cross(v, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    w = np.cross(v, u)
    ax = np.asarray(PH.skin_semi_axes_mm, float)
    more = []
    for ang in np.radians([40, 48, 56, 64]):
        for e in (u, -u, w, -w):
            d = np.cos(ang) * v + np.sin(ang) * e
            more.append(PH.centre_lps + d / np.sqrt(np.sum((d / ax) ** 2)))
    pr = replace(problem, existing=np.vstack([PH.fiducial_centres_lps, more]))
    ids = tuple(100 + 3 * i for i in range(len(pr.existing)))
    named = plan_layout(pr, 7, n_directions=8, refine=False, fiducial_ids=ids)
    ex = named.existing_here               # the CT's balls from the planned camera, by position
    which = [int(np.argmin(np.linalg.norm(pr.existing - c, axis=1))) for c in ex.centres]
    want = tuple(ids[which[i]] for i in np.flatnonzero(ex.visibility.short_of_skin))
    assert want, ex.visibility.skin_around
    assert named.outline_fiducials == want
    note = next(n for n in named.notes if n.startswith("CT fiducial"))
    assert {int(m) for m in re.findall(r"#(\d+)", note)} == set(named.outline_fiducials)
    with pytest.raises(ValueError, match="fiducial ids"):
        plan_layout(pr, 7, n_directions=8, refine=False, fiducial_ids=ids[:-1])


def test_exchange_search_finds_the_exhaustive_optimum(problem):
    """On a pool of 13 usable positions, the search's 6-ball layout is the best of all 1716."""
    cands = sample_candidates(problem, spacing_mm=20.0)
    pose = camera_pose(PH.view_direction_lps, 450.0, PH.fiducial_centres_lps.mean(axis=0), cands.skin)
    pd = pose_data(problem, cands, pose)
    pool = np.flatnonzero(pd.usable)
    rng = np.random.default_rng(2)
    pool = np.sort(rng.choice(pool, 13, replace=False))
    pd.usable[:] = False
    pd.usable[pool] = True
    sep = problem.min_separation_mm
    layouts = [c for c in itertools.combinations(pool, 6)
               if all(np.linalg.norm(cands.centres[a] - cands.centres[b]) >= sep for a, b in itertools.combinations(c, 2))]
    assert len(layouts) > 500
    assert np.isfinite(values := objective(pd, np.array(layouts), points=cands.centres)).sum() > 100
    S, val = best_layout(pd, cands.centres, 6, sep)
    assert val == pytest.approx(float(values.min()), rel=1e-6), (val, values.min())
    # ties are real: two layouts that differ only in the ball whose loss is the worst case leave
    # the same five balls, hence the same objective
    best = [sorted(c) for c, v in zip(layouts, values) if v <= values.min() * (1 + 1e-9)]
    assert sorted(S) in best, (S, best)
    # and the objective is the prediction's "worst single ball hidden", squared, at 1 px, without the
    # shading cover (left out of the ranking: search.py)
    p = predict(replace(problem, noise_px=1.0, edge_rms_px=0.0), pose.T_ct_cam, cands.centres[S], cands.normals[S])
    assert np.sqrt(val) == pytest.approx(p.worst_hidden.rms_mm, rel=1e-6)


def test_plan_keeps_the_rules_and_the_camera_space(problem, quick_plan):
    """Every suggested ball on exposed skin, clear of the incision and the path, two ball
    diameters from the others, seen from the planned camera; the camera inside the cone and the
    distance range and out of the robot's reach."""
    plan, P = quick_plan, problem
    B = plan.balls
    assert B.shape == (7, 3)
    r = P.radius_mm
    d = np.linalg.norm(B[:, None] - B[None], axis=2) + np.eye(len(B)) * 1e9
    assert d.min() >= 4.0 * r - 1e-9
    assert np.all((B - PH.centre_lps) @ PH.view_direction_lps >= 0.0)          # drape through the centre
    assert np.all(np.linalg.norm(B - P.entry, axis=1) >= P.rules.incision_clearance_mm + r - 1e-9)
    # distance to the path's line, computed here from scratch
    u = (P.entry - P.target) / np.linalg.norm(P.entry - P.target)
    t = np.clip((B - P.target) @ u, 0.0, np.linalg.norm(P.entry - P.target) + P.rules.path_extension_mm)
    assert np.all(np.linalg.norm(B - (P.target + t[:, None] * u), axis=1) >= P.rules.path_clearance_mm + r - 1e-9)
    # on the skin: the centre one radius out of the ellipsoid (|x/a| = 1 at the skin point)
    skin = B - r * plan.normals
    q = np.linalg.norm((skin - PH.centre_lps) / PH.skin_semi_axes_mm, axis=1)
    assert np.all(np.abs(q - 1.0) < 0.01)
    assert plan.expected.visibility.count == 7
    eye = plan.T_ct_cam[:3, 3]
    # each ball seen from the planned camera within the placement limit of its skin normal (the
    # ellipsoid's normal, from scratch): no suggested ball the camera grazes
    n_skin = (skin - PH.centre_lps) / PH.skin_semi_axes_mm**2
    n_skin /= np.linalg.norm(n_skin, axis=1, keepdims=True)
    sight = (eye - B) / np.linalg.norm(eye - B, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.sum(sight * n_skin, axis=1)))
    assert angle.max() <= PLACE_MAX_VIEW_ANGLE_DEG + 0.5, angle
    look = plan.T_ct_cam[:3, 2]
    aim = plan.camera.aim
    assert np.degrees(np.arccos((eye - aim) @ P.space.axis / np.linalg.norm(eye - aim))) <= P.space.half_angle_deg + 1e-6
    assert P.space.distance_mm[0] - 1e-6 <= np.linalg.norm(eye - aim) <= P.space.distance_mm[1] + 1e-6
    assert look @ (aim - eye) / np.linalg.norm(aim - eye) > 0.999
    for k in P.space.keep_out:
        assert k.distance(eye)[0] >= k.radius_mm + P.space.clearance_mm
    # what to expect: nearer is better, a hidden ball costs
    e = plan.expected
    assert e.worst_hidden.rms_mm >= e.all_seen.rms_mm
    assert plan.at_near.all_seen.rms_mm <= plan.at_far.all_seen.rms_mm
    assert plan.existing_here is not None and plan.existing_best is not None
    assert len(plan.moves) == 7 and sorted(m[1] for m in plan.moves) == list(range(7))
    assert np.isfinite(plan.error_map_mm).sum() > 50
    assert np.nanmin(plan.error_map_mm) <= e.worst_hidden.rms_mm + 1e-9
    # and with the detector's losses (each seen ball found at the measured rate): fewer trusted
    lo = e.with_losses
    assert lo is not None and lo.found_probability == P.found_probability
    assert 0.0 <= lo.trusted < e.all_seen.trusted and 0.0 < lo.pose < 1.0
    assert any(f"expect a pose in {100 * lo.pose:.0f} % of setups like this" in n for n in plan.notes)
    # and it is said to be an estimate, with the range measured on rendered scenes
    from monotracker.planning.detector_defaults import OUTLOOK_OBSERVED_RANGE_POINTS as rng
    assert rng[0] < 0 < rng[1]
    assert any(f"outcome lay {-rng[0]} points below to {rng[1]} above it" in n for n in plan.notes)
    # and the known limit of the trust on such layouts (docs/vision.md, "Longer streams")
    from monotracker.planning.detector_defaults import PLANNED_LAYOUT_GATE_OFF as gate
    from monotracker.planning.detector_defaults import PLANNED_LAYOUT_TRACKER_OFF as trk

    assert 0 <= trk[0] <= trk[1] and 0 <= gate[0] <= gate[1] <= trk[1]
    assert any(f"trusted {trk[0]} of {trk[1]} frames 1-2 mm off at the target, and {gate[0]} of the {gate[1]} poses "
               "that would move the arm" in n for n in plan.notes)
    assert plan.to_dict()["expected"]["with_detector_losses"]["trusted_fraction"] == round(lo.trusted, 4)
    assert plan.at_near.with_losses is None        # asked for only where it is shown
    # how many balls reach 85 % with those losses from this camera: that count's layout does (the
    # full outlook, 12 subsets per count, against the search's 4), the count one fewer does not
    from monotracker.planning.planner import MIN_TRUSTED_WITH_LOSSES
    from monotracker.planning.prediction import outlook_with_losses

    k = plan.balls_for_losses
    assert k is not None and 7 < k <= 16 and any(f"{k} balls reach 85 %" in n for n in plan.notes), plan.notes
    pd = pose_data(P, plan.candidates, plan.camera)
    def share(m):
        S, _ = best_layout(pd, plan.candidates.centres, m, P.min_separation_mm, np.array([], int), 4, max_passes=2)
        return outlook_with_losses(P, plan.T_ct_cam, plan.candidates.centres[S], np.ones(len(S), bool)).trusted
    assert share(k) >= MIN_TRUSTED_WITH_LOSSES - 0.05, share(k)
    assert k == 8 or share(k - 1) < MIN_TRUSTED_WITH_LOSSES + 0.05
    assert plan.to_dict()["balls_for_losses"] == k


def _measure(T_cam_ct, X, target, noise, frames=120, seed=0, hide=None):
    """(RMS error at the target over trusted frames mm, trusted share) through the real PoseTracker
    fed noisy exact ellipse centres of the balls X (``hide``: a ball index left out of the image;
    the tracker still knows it)."""
    from monotracker.vision.camera_model import default_camera

    cam = default_camera()
    det = PointDetector()
    tr = PoseTracker(X, cam, detector=det, radius_mm=4.0, target_ct=target)
    rng = np.random.default_rng(seed)
    err, ok = [], 0
    Xc = X @ T_cam_ct[:3, :3].T + T_cam_ct[:3, 3]
    px0 = _to_pixels(ellipse_centre_normalised(Xc, 4.0), cam.K, cam.dist)
    for k in range(frames):
        shown = np.arange(len(X)) != (-1 if hide is None else hide)
        det.set((px0 + rng.normal(scale=noise, size=px0.shape))[shown], (cam.K[0, 0] * 4.0 / Xc[:, 2])[shown])
        e = tr.process(Frame(BLANK, k / 30.0, k))
        if e.ok:
            ok += 1
            err.append(tre_mm(e.T_cam_ct, T_cam_ct, target[None])[0])
    return float(np.sqrt(np.mean(np.square(err)))) if err else np.inf, ok / frames


def test_a_layout_called_better_measures_better(problem, quick_plan):
    """The planned layout against the rule of thumb (the same count spread evenly over the
    skin the planned camera sees) and seven of the phantom's own balls it sees, from the planned camera,
    on what the planner minimises (the error at the target with the worst single ball hidden): the
    predicted order is the measured order, and each measured RMS (all seen, each ball hidden in
    turn) is near its prediction."""
    plan = quick_plan
    T_ct_cam = plan.T_ct_cam
    T_cam_ct = invert_transform(T_ct_cam)
    thumb = rule_of_thumb_layout(problem, T_ct_cam, 7)
    kit = PH.fiducial_centres_lps
    kit_seen = predict(problem, T_ct_cam, kit).visibility.seen     # the planned camera need not see all nine
    assert kit_seen.sum() >= 7, kit_seen
    layouts = {"planned": plan.balls, "rule of thumb": thumb, "phantom's": kit[kit_seen][:7]}
    noise = 0.3
    pred, meas = {}, {}
    for name, X in layouts.items():
        p = predict(replace(problem, noise_px=noise), T_ct_cam, X)
        assert p.visibility.count == len(X), (name, p.visibility.why)
        all_seen, _ = _measure(T_cam_ct, X, problem.target, noise, seed=len(name))
        assert all_seen == pytest.approx(p.all_seen.rms_mm, rel=0.25), (name, all_seen, p.all_seen.rms_mm)
        # each ball hidden in turn, measured against the model without that ball: where the model
        # trusts the rest in at least half the frames the measured RMS is near its prediction; where
        # they give no pose, no frame is trusted (where the model trusts them in fewer frames, the
        # tracker, which pools a still head's frames, may trust more: the safe side)
        hid = [_measure(T_cam_ct, X, problem.target, noise, frames=60, seed=10 * i + len(name), hide=i)
               for i in range(len(X))]
        without = [predict(replace(problem, noise_px=noise), T_ct_cam, np.delete(X, i, axis=0)).all_seen
                   for i in range(len(X))]
        for i, ((r, t), m) in enumerate(zip(hid, without)):
            if m is None:
                assert t == 0.0, (name, i, t)
            elif m.trusted >= 0.5:
                assert r == pytest.approx(m.rms_mm, rel=0.25), (name, i, r, t, m.rms_mm, m.trusted)
        # the worst single hidden ball: inf where losing some ball leaves the pose mostly untrusted
        meas[name] = max(r if t >= 0.25 else np.inf for r, t in hid)
        pred[name] = max(m.rms_mm if m is not None and m.trusted >= 0.5 else np.inf for m in without)
        w = p.worst_hidden
        if w is None:                      # the model: some ball's loss loses the pose
            assert not np.isfinite(pred[name]), (name, p.margin_reason)
    assert np.isfinite(pred["planned"]) and np.isfinite(meas["planned"]), (pred, meas)
    assert pred["planned"] < pred["rule of thumb"] and pred["planned"] < pred["phantom's"]
    assert meas["planned"] < meas["rule of thumb"] and meas["planned"] < meas["phantom's"], (meas, pred)
