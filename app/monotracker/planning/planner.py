"""The layout planner: where to put the balls and the camera so the error at the target is small,
with a margin for losing any one ball.

:func:`plan_layout` runs, for a :class:`~.problem.PlanningProblem` and a ball count:

1. candidates on the skin (:mod:`.candidates`) and camera poses in the camera space
   (:mod:`.camera_poses`: a cone of directions x the near and far ends of the distance range);
2. per pose, which candidates it sees (:mod:`.visibility`) and each one's share of the pose
   fit's normal matrix (the registration's Jacobian); a quick layout (seed + greedy) per pose;
3. the exchange search (:mod:`.search`) on the most promising poses; the best wins;
4. the camera refined around it (finer directions and distances, the layout fixed), and the
   layout exchanged once more there;
5. what to expect (:mod:`.prediction`): the error at the target with every ball seen and with
   the worst one hidden, the outlook with the detector's losses (:mod:`.ball_losses`; for the
   suggestion and the CT's balls from the planned camera), at the camera's distance limits, for
   the CT's own fiducials (from the
   planned camera and from the best camera for them), the moves from the CT's balls to the
   suggestion, a map of the error per candidate position, and, when the trusted share stays
   under ``min_trusted``, how many balls it would take; in a full plan whose outlook with the
   detector's losses stays under ``MIN_TRUSTED_WITH_LOSSES``, how many balls reach that.

``progress(fraction, message)`` is called along the way; it may raise to cancel (the engine's
job token does). Units: LPS mm, px; poses ``T_ct_cam``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from monotracker.geometry import invert_transform
from monotracker.registration.report import fiducial_information
from monotracker.vision.lens_range import short_lens_message
from monotracker.vision.tracker_config import TrackerConfig

from .camera_poses import CameraPose, camera_pose, candidate_poses, cone_directions
from .candidates import Candidates, sample_candidates
from .detector_defaults import OUTLOOK_OBSERVED_RANGE_POINTS, PLANNED_LAYOUT_GATE_OFF, PLANNED_LAYOUT_TRACKER_OFF
from .prediction import Prediction, outlook_with_losses, predict
from .problem import PlanningProblem
from .search import PoseData, best_layout, objective, spread_seed, swap_map
from .visibility import PLACE_MAX_VIEW_ANGLE_DEG, visibility

#: the trusted share a plan should reach (the issue's 95 %)
MIN_TRUSTED = 0.95
#: most balls the planner will suggest when asked how many it takes
MAX_BALLS = 16
#: the trusted share with the detector's losses a full plan asks how many balls reach (the
#: issue 28 reach target for OR, degraded and clutter scenes: 85 % of setups)
MIN_TRUSTED_WITH_LOSSES = 0.85
#: subsets per count of lost balls in that count's search (the reported outlook uses 12)
LOSS_SEARCH_SUBSETS = 4


@dataclass(frozen=True)
class LayoutPlan:
    """The planner's answer (LPS mm, ``T_ct_cam`` 4x4).

    ``balls`` (n, 3) suggested centres, ``normals`` (n, 3) their skin normals, ``from_existing``
    (n,) the CT fiducial index a suggested ball is (kept where it is), -1 for a new position;
    ``camera`` the planned :class:`~.camera_poses.CameraPose`; ``expected`` its
    :class:`~.prediction.Prediction`; ``at_near`` / ``at_far`` the same layout with the camera at
    the near / far end of the distance range (same direction and aim); ``existing_here`` /
    ``existing_best`` the CT's own fiducials from the planned camera / from the best camera
    for them (None without CT fiducials); ``moves`` (CT fiducial index, suggested ball index,
    distance mm) pairing the CT's balls with the suggestion (Hungarian, smallest total move);
    ``candidates`` and ``error_map_mm`` (m,) the RMS error at the target with the worst ball
    hidden if one ball moved to each candidate (NaN: not usable from the planned camera);
    ``balls_needed`` the smallest count whose plan is trusted in ``min_trusted`` of frames with
    a ball hidden (None when this plan already is, or not even ``MAX_BALLS`` would);
    ``balls_for_losses`` the smallest count whose layout from this camera reaches
    ``MIN_TRUSTED_WITH_LOSSES`` with the detector's losses (full plans whose outlook is under
    it; None otherwise or when not even ``MAX_BALLS`` would: the notes say which);
    ``notes`` one-line remarks; ``outline_fiducials`` the CT fiducials (their indices, or the
    ``fiducial_ids`` :func:`plan_layout` was given) the planned camera sees with too little skin
    around them (``Visibility.short_of_skin``; a note names them)."""

    problem: PlanningProblem
    balls: np.ndarray
    normals: np.ndarray
    from_existing: np.ndarray
    camera: CameraPose
    expected: Prediction
    at_near: Prediction
    at_far: Prediction
    existing_here: Prediction | None
    existing_best: Prediction | None
    existing_best_camera: CameraPose | None
    moves: tuple
    candidates: Candidates
    error_map_mm: np.ndarray
    balls_needed: int | None
    notes: tuple = field(default_factory=tuple)
    balls_for_losses: int | None = None
    outline_fiducials: tuple = ()

    @property
    def T_ct_cam(self) -> np.ndarray:
        return self.camera.T_ct_cam

    def to_dict(self) -> dict:
        """JSON-ready summary (lists and floats)."""
        def pred(p):
            return None if p is None else p.to_dict()

        return {
            "frame": "LPS", "units": "mm",
            "target_lps_mm": np.round(self.problem.target, 3).tolist(),
            "entry_lps_mm": None if self.problem.entry is None else np.round(self.problem.entry, 3).tolist(),
            "ball_radius_mm": self.problem.radius_mm, "noise_px": self.problem.noise_px,
            "balls_lps_mm": np.round(self.balls, 3).tolist(),
            "balls_from_existing": [int(i) for i in self.from_existing],
            "T_ct_cam": np.round(self.T_ct_cam, 6).tolist(),
            "camera_distance_mm": round(self.camera.distance_mm, 1),
            "expected": pred(self.expected),
            "at_near_distance": pred(self.at_near), "at_far_distance": pred(self.at_far),
            "existing_from_planned_camera": pred(self.existing_here),
            "existing_from_their_best_camera": pred(self.existing_best),
            "moves": [{"ct_fiducial": int(a), "to_ball": int(b), "distance_mm": round(float(d), 1)}
                      for a, b, d in self.moves],
            "balls_needed": self.balls_needed, "balls_for_losses": self.balls_for_losses,
            "notes": list(self.notes),
            "ct_fiducials_short_of_skin": list(self.outline_fiducials),
        }


class _Progress:
    def __init__(self, fn):
        self.fn = fn

    def __call__(self, frac: float, msg: str) -> None:
        if self.fn is not None:
            self.fn(float(min(max(frac, 0.0), 1.0)), msg)


def placeable(vis, cands: Candidates, idx=None) -> np.ndarray:
    """(m,) bool: a NEW ball may go at candidates ``idx`` (all when None) whose visibility is
    ``vis``: seen, allowed by the rules, seen within ``PLACE_MAX_VIEW_ANGLE_DEG`` of its skin
    normal (a ball the camera grazes is measured with a bias) and with skin around it in the
    camera's view (``PLACE_MIN_SKIN_AROUND``: not on the head's outline, not beside the drape,
    where the detector loses balls; see :mod:`.visibility`)."""
    allowed = cands.allowed if idx is None else cands.allowed[np.asarray(idx, int)]
    return vis.seen & allowed & (vis.view_angle_deg <= PLACE_MAX_VIEW_ANGLE_DEG) & ~vis.short_of_skin


def pose_data(problem: PlanningProblem, cands: Candidates, pose: CameraPose) -> PoseData:
    """Visibility and each candidate's normal-matrix share (px^2 units) from ``pose``."""
    vis = visibility(problem, pose.T_ct_cam, cands.centres, cands.normals)
    T_cam_ct = invert_transform(pose.T_ct_cam)
    info = np.zeros((len(cands), 6, 6))
    if vis.count:
        fxy = np.array([problem.camera.K[0, 0], problem.camera.K[1, 1]])
        info[vis.seen] = fiducial_information(T_cam_ct, cands.centres[vis.seen], fxy, problem.radius_mm)
    return PoseData(T_cam_ct, info, vis.seen.copy(), placeable(vis, cands), problem.target)


def plan_layout(problem: PlanningProblem, n_balls: int = 9, keep: tuple = (), progress=None,
                n_directions: int = 24, refine: bool = True, min_trusted: float = MIN_TRUSTED,
                config: TrackerConfig | None = None, candidates: Candidates | None = None,
                fiducial_ids: tuple | None = None) -> LayoutPlan:
    """Plan ``n_balls`` balls and the camera for ``problem`` (see the module docstring).

    Args:
        problem: the :class:`~.problem.PlanningProblem` (checked: :meth:`~.problem.PlanningProblem.problem`).
        n_balls: how many balls (the user's choice), 4..``MAX_BALLS``.
        keep: indices of the CT's fiducials (``problem.existing``) that stay where they are.
        progress: ``progress(fraction, message)`` or None; may raise to cancel.
        n_directions: viewing directions tried over the cone.
        refine: refine the camera around the best pose (off: quicker, coarser).
        min_trusted: the trusted share the plan should reach (for ``balls_needed``).
        config: the pose stream's gates (defaults: ``TrackerConfig()``).
        candidates: precomputed :func:`~.candidates.sample_candidates` (None: computed here).
        fiducial_ids: the names of the CT's fiducials (``problem.existing``, in order) in the
            plan's notes and ``outline_fiducials`` (None: their indices), e.g. the app's plan ids.

    Returns:
        :class:`LayoutPlan`.

    Raises:
        ValueError: one line: the problem cannot be planned, a bad count or keep index, no
            camera pose is allowed, or too few usable positions.
    """
    cfg = config or TrackerConfig()
    why = problem.problem()
    if why:
        raise ValueError(why)
    n = int(n_balls)
    if not (cfg.min_fiducials <= n <= MAX_BALLS):
        raise ValueError(f"ball count must be {cfg.min_fiducials}-{MAX_BALLS}, got {n_balls}")
    keep = tuple(int(i) for i in keep)
    if fiducial_ids is not None and len(fiducial_ids) != len(problem.existing):
        raise ValueError(f"{len(fiducial_ids)} fiducial ids for {len(problem.existing)} CT fiducials")
    if any(i < 0 or i >= len(problem.existing) for i in keep) or len(set(keep)) != len(keep):
        raise ValueError(f"keep must name distinct CT fiducials 0-{len(problem.existing) - 1}")
    if len(keep) > n:
        raise ValueError(f"{len(keep)} balls kept but only {n} asked for")
    prog = _Progress(progress)
    prog(0.0, "candidate positions on the skin")
    cands = candidates if candidates is not None else sample_candidates(problem)
    if int(cands.allowed.sum()) + len(keep) < n:
        raise ValueError(f"only {int(cands.allowed.sum())} allowed positions on the skin for {n} balls; "
                         "widen the region or lower the clearances")
    keep_idx = tuple(int(np.flatnonzero(cands.existing == i)[0]) for i in keep)
    poses = candidate_poses(problem.space, problem.head.centre, cands.skin, cands.normals, n_directions)
    if not poses:
        raise ValueError("no camera pose is allowed: the camera space is all occupied or inside the robot's reach")
    min_sep = problem.min_separation_mm
    quick = []
    for i, pose in enumerate(poses):
        prog(0.05 + 0.5 * i / len(poses), f"camera pose {i + 1} of {len(poses)}")
        pd = pose_data(problem, cands, pose)
        S, val = best_layout(pd, cands.centres, n, min_sep, keep_idx, cfg.min_fiducials, exchange=False)
        quick.append((val if len(S) == n else np.inf, i, pd))
    quick.sort(key=lambda t: t[0])
    if not np.isfinite(quick[0][0]):
        raise ValueError(f"no camera pose sees {n} usable positions with a pose to spare; "
                         "widen the camera cone or the allowed region, or use fewer balls")
    best = None
    top = [q for q in quick[:4] if np.isfinite(q[0])]
    for j, (_, i, pd) in enumerate(top):
        prog(0.55 + 0.2 * j / len(top), f"exchange search at camera pose {j + 1} of {len(top)}")
        S, val = best_layout(pd, cands.centres, n, min_sep, keep_idx, cfg.min_fiducials)
        if best is None or val < best[0]:
            best = (val, poses[i], pd, S)
    val, pose, pd, S = best
    if refine:
        prog(0.78, "refining the camera placement")
        pose, pd, S, val = _refine_camera(problem, cands, pose, S, val, n, min_sep, keep_idx, cfg)
    prog(0.88, "what to expect")
    plan = _expectations(problem, cands, pose, pd, S, keep_idx, quick, poses, cfg, min_trusted, n,
                         None if fiducial_ids is None else tuple(int(i) for i in fiducial_ids))
    outlook = plan.expected.with_losses
    if refine and outlook is not None and outlook.trusted < MIN_TRUSTED_WITH_LOSSES:
        prog(0.94, "how many balls with the detector's losses")
        k = _balls_for_losses(problem, cands, pd, n, keep_idx, cfg, MIN_TRUSTED_WITH_LOSSES)
        target = f"{100 * MIN_TRUSTED_WITH_LOSSES:.0f} % trusted frames with the detector's losses"
        note = (f"{k} balls reach {target} from this camera" if k is not None else
                f"not even {MAX_BALLS} balls reach {target} from this camera: bring it nearer")
        plan = replace(plan, balls_for_losses=k, notes=plan.notes + (note,))
    prog(1.0, "layout planned")
    return plan


def _balls_for_losses(problem, cands, pd, n, keep_idx, cfg, target) -> int | None:
    """The smallest count above ``n`` whose layout from this camera reaches ``target`` trusted
    share with the detector's losses (:func:`~.prediction.outlook_with_losses`,
    :data:`LOSS_SEARCH_SUBSETS` subsets per count of lost balls; :func:`_smallest_count`). Full
    plans only (1-3 s per count)."""
    def reaches(T_ct_cam, S) -> bool:
        seen = np.ones(len(S), bool)       # the search places balls only where this camera sees them
        # (new balls only with skin all round; a kept CT ball may be short of it)
        short = visibility(problem, T_ct_cam, cands.centres[S], cands.normals[S]).short_of_skin
        o = outlook_with_losses(problem, T_ct_cam, cands.centres[S], seen, config=cfg, short_of_skin=short,
                                per_count=LOSS_SEARCH_SUBSETS)
        return o.trusted >= target

    return _smallest_count(problem, cands, pd, n, keep_idx, cfg, reaches)


def _refine_camera(problem, cands, pose, S, val, n, min_sep, keep_idx, cfg):
    """Finer directions (a cone of half the grid's spacing around the best) and distances over
    the range, the layout fixed; then one exchange search at the best of them."""
    space = problem.space
    spacing = space.half_angle_deg * np.sqrt(np.pi / max(len(cone_directions(space.axis, space.half_angle_deg, 24)), 1))
    dirs = cone_directions(pose.direction, max(spacing, 1.0), 9)
    cos_lim = np.cos(np.radians(space.half_angle_deg))
    lo, hi = space.distance_mm
    best = (val, pose, None)
    L = np.array([S])
    for d in dirs:
        if d @ space.axis < cos_lim - 1e-9:
            continue
        for dist in np.linspace(lo, hi, 5):
            p = camera_pose(d, dist, pose.aim, cands.skin[cands.normals @ d > 0.5])
            if space.where_not(p.eye, problem.head.centre):
                continue
            pd = pose_data_subset(problem, cands, p, S)
            if not all(pd.usable[i] or i in keep_idx for i in S):
                continue     # this camera would graze a suggested ball (or lose it)
            v = float(objective(pd, L, cfg.min_fiducials, cands.centres)[0])
            if v < best[0] * (1 - 1e-9):
                best = (v, p, None)
    pose = best[1]
    pd = pose_data(problem, cands, pose)
    S2, v2 = best_layout(pd, cands.centres, n, min_sep, keep_idx, cfg.min_fiducials)
    if v2 <= best[0]:
        return pose, pd, S2, v2
    return pose, pd, S, float(objective(pd, L, cfg.min_fiducials, cands.centres)[0])


def pose_data_subset(problem, cands, pose, idx) -> PoseData:
    """:func:`pose_data` for the candidates ``idx`` only (the others unseen): a quick look."""
    idx = np.asarray(idx, int)
    m = len(cands)
    vis = visibility(problem, pose.T_ct_cam, cands.centres[idx], cands.normals[idx])
    seen = np.zeros(m, bool)
    seen[idx[vis.seen]] = True
    usable = np.zeros(m, bool)
    usable[idx[placeable(vis, cands, idx)]] = True
    T_cam_ct = invert_transform(pose.T_ct_cam)
    info = np.zeros((m, 6, 6))
    if vis.count:
        fxy = np.array([problem.camera.K[0, 0], problem.camera.K[1, 1]])
        info[idx[vis.seen]] = fiducial_information(T_cam_ct, cands.centres[idx[vis.seen]], fxy, problem.radius_mm)
    return PoseData(T_cam_ct, info, seen, usable, problem.target)


def _expectations(problem, cands, pose, pd, S, keep_idx, quick, poses, cfg, min_trusted, n,
                  names: tuple | None = None) -> LayoutPlan:
    """The plan of layout ``S`` from ``pose`` with what to expect (``names``: the CT fiducials'
    names in its notes, None: their indices)."""
    balls, normals = cands.centres[S], cands.normals[S]
    expected = predict(problem, pose.T_ct_cam, balls, normals, config=cfg, losses=True)
    lo, hi = problem.space.distance_mm
    spread = cands.skin[cands.normals @ pose.direction > 0.5]
    near = camera_pose(pose.direction, lo, pose.aim, spread)
    far = camera_pose(pose.direction, hi, pose.aim, spread)
    at_near = predict(problem, near.T_ct_cam, balls, normals, config=cfg)
    at_far = predict(problem, far.T_ct_cam, balls, normals, config=cfg)
    ex_here = ex_best = ex_cam = None
    moves = ()
    n_ex = len(problem.existing)
    if n_ex:
        ex = np.flatnonzero(cands.existing >= 0)
        ex_here = predict(problem, pose.T_ct_cam, cands.centres[ex], cands.normals[ex], config=cfg, losses=True)
        # the best camera for the CT's own balls, among the poses tried
        L = np.array([ex])
        vals = [(float(objective(q[2], L, cfg.min_fiducials, cands.centres)[0]), q[1]) for q in quick]
        v, i = min(vals)
        ex_cam = poses[i]
        ex_best = predict(problem, ex_cam.T_ct_cam, cands.centres[ex], cands.normals[ex], config=cfg)
        moves = _moves(problem.existing, balls)
    emap = np.sqrt(swap_map(pd, cands.centres, S, problem.min_separation_mm, keep_idx, cfg.min_fiducials))
    # at the planned noise with the shading cover (its floor scales every entry alike; the common
    # shift, absorbed by a translation parallel to the image, is nearly the same for every layout
    # from one camera pose: the suggestion's is added to each)
    ref = expected.worst_hidden or expected.all_seen
    floor, c0 = (ref.floor_px, ref.common_mm2) if ref is not None else (0.0, 0.0)
    emap = np.sqrt(emap**2 * max(problem.noise_px, floor) ** 2 + c0)
    if ref is not None:      # the suggestion's own positions show exactly what is promised for it
        emap[np.asarray(S, int)] = ref.rms_mm
    notes = []
    if n < cfg.min_fiducials + 1:
        notes.append(f"with {n} balls losing any one loses the pose; take at least {cfg.min_fiducials + 1}")
    elif n == cfg.min_fiducials + 1:
        notes.append(f"with {n} balls one hidden leaves {cfg.min_fiducials}: matching 4 balls is refused as "
                     "ambiguous in about 40 % of frames (README, Registration); 6 or more is safer")
    needed = None
    worst = expected.worst_hidden
    if worst is None or worst.trusted < min_trusted:
        needed = _balls_needed(problem, cands, pd, n, keep_idx, cfg, min_trusted)
        if needed is None:
            notes.append(f"not even {MAX_BALLS} balls reach {100 * min_trusted:.0f} % trusted frames with one "
                         "hidden from this camera: bring the camera nearer, lower the noise or move the target")
        else:
            notes.append(f"{needed} balls reach {100 * min_trusted:.0f} % trusted frames with one hidden")
    outlook = expected.with_losses
    if outlook is not None:
        notes.append(f"with the detector's losses on realistic frames (gloves, instruments, shading; "
                     f"{outlook.phrase}, calibrated on rendered frames) "
                     f"expect a pose in {100 * outlook.pose:.0f} % of setups like this and trusted frames in "
                     f"{100 * outlook.trusted:.0f} %; more balls or a nearer camera raise both. An estimate: on "
                     f"rendered test scenes the outcome lay {-OUTLOOK_OBSERVED_RANGE_POINTS[0]} points below to "
                     f"{OUTLOOK_OBSERVED_RANGE_POINTS[1]} above it. A known limit: on rendered frames of such "
                     f"planned layouts the pose tracker trusted {PLANNED_LAYOUT_TRACKER_OFF[0]} of "
                     f"{PLANNED_LAYOUT_TRACKER_OFF[1]} frames 1-2 mm off at the target, and "
                     f"{PLANNED_LAYOUT_GATE_OFF[0]} of the {PLANNED_LAYOUT_GATE_OFF[1]} poses that would move the arm "
                     "(none over 2 mm)")
    lens = short_lens_message(problem.camera, problem.radius_mm, lo)   # at the planner's own closest distance
    if lens:
        notes.append(lens)
    outline_ids = ()
    if ex_here is not None:
        ct_idx = cands.existing[np.flatnonzero(cands.existing >= 0)]
        names = range(len(problem.existing)) if names is None else names
        outline_ids = tuple(int(names[ct_idx[i]]) for i in np.flatnonzero(ex_here.visibility.short_of_skin))
    if outline_ids:
        notes.append(_outline_note(outline_ids))
    from_existing = cands.existing[S]
    return LayoutPlan(problem, balls, normals, from_existing, pose, expected, at_near, at_far, ex_here, ex_best,
                      ex_cam, moves, cands, emap, needed, tuple(notes), outline_fiducials=outline_ids)


def _outline_note(ct_ids: tuple) -> str:
    """The note naming the CT fiducials ``ct_ids`` (their names, at least one) that the planned
    camera sees with too little skin around them (``Visibility.short_of_skin``)."""
    names = ", ".join(f"#{i}" for i in ct_ids)
    return (f"CT fiducial{'s' if len(ct_ids) > 1 else ''} {names}: on the head's outline or beside the drape in the "
            "planned camera's view (little skin around in the image); the detector often loses such balls (on "
            "rendered frames found about a quarter as often as balls with skin all round), so the planner puts no "
            "new ball where this is so and counts them as found less often")


def _balls_needed(problem, cands, pd, n, keep_idx, cfg, min_trusted) -> int | None:
    """The smallest count above ``n`` whose layout from this camera is trusted in
    ``min_trusted`` of frames with the worst ball hidden (:func:`_smallest_count`)."""
    def reaches(T_ct_cam, S) -> bool:
        p = predict(problem, T_ct_cam, cands.centres[S], cands.normals[S], config=cfg)
        return p.worst_hidden is not None and p.worst_hidden.trusted >= min_trusted

    return _smallest_count(problem, cands, pd, n, keep_idx, cfg, reaches)


def _smallest_count(problem, cands, pd, n, keep_idx, cfg, reaches) -> int | None:
    """The smallest ball count above ``n`` (up to ``MAX_BALLS``) whose exchange-search layout
    ``S`` (candidate indices) from the camera of ``pd`` satisfies ``reaches(T_ct_cam, S)``;
    None when none does or the skin holds no more balls."""
    T_ct_cam = invert_transform(pd.T_cam_ct)
    for k in range(n + 1, MAX_BALLS + 1):
        S, _ = best_layout(pd, cands.centres, k, problem.min_separation_mm, keep_idx, cfg.min_fiducials, max_passes=2)
        if len(S) < k:
            return None
        if reaches(T_ct_cam, S):
            return k
    return None


def _moves(existing: np.ndarray, balls: np.ndarray) -> tuple:
    """(CT fiducial, suggested ball, distance mm) pairs with the smallest total distance."""
    from scipy.optimize import linear_sum_assignment

    d = np.linalg.norm(existing[:, None] - balls[None], axis=2)
    r, c = linear_sum_assignment(d)
    return tuple((int(a), int(b), float(d[a, b])) for a, b in zip(r, c))


def rule_of_thumb_layout(problem: PlanningProblem, T_ct_cam: np.ndarray, n_balls: int,
                         candidates: Candidates | None = None) -> np.ndarray:
    """The rule of thumb, for comparison: ``n_balls`` spread as evenly and widely as possible
    (farthest-point sampling) over the allowed skin the camera at ``T_ct_cam`` sees, without
    looking at the target, on the same skin the planner may use (seen within
    ``PLACE_MAX_VIEW_ANGLE_DEG`` of the normal: nobody sticks a ball where the camera grazes the
    skin), so the two differ in where they put the balls, not in which skin they may use.
    (n, 3) centres LPS mm."""
    cands = candidates if candidates is not None else sample_candidates(problem)
    vis = visibility(problem, T_ct_cam, cands.centres, cands.normals)
    pool = np.flatnonzero(placeable(vis, cands))
    S = spread_seed(cands.centres, pool, int(n_balls), problem.min_separation_mm)
    return cands.centres[S]
