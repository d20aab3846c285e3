"""What to expect when the detector does not find every ball the camera sees.

The planner's other figures assume every ball the camera sees is found (``all_seen``), or all
but the one whose loss hurts most (``worst_hidden``). On physically rendered frames the default
detector matches about half of the balls a camera sees after 8 frames (gloved fingers,
instruments, strays and shading included; ``docs/planning.md``, "The detector's losses"): every
one of 36 planner-placed tuning scenes was predicted trusted in >= 95 % of frames with one ball
hidden, and 20-50 % were trusted after 8 frames.

:func:`loss_outlook` models each seen ball as found independently with probability
``found_probability`` (the planning problem's; by default
:data:`~.detector_defaults.DEFAULT_FOUND_PROBABILITY`, calibrated on rendered frames) and
averages, over which balls are found, the tracker's trusted share of frames
(:func:`~.prediction.outlook_with_losses` with :func:`~.prediction.predict_error`, the same model
as ``all_seen``): the share of setups like this one whose pose the stream trusts, and the
probability that enough balls are found for a pose at all. A ball the detector loses in one
frame of a still head is mostly lost in the next ones too (the same shading, the same glove), so
the average is over setups, not over frames. Exact over every subset when there are few of them;
otherwise a fixed number of subsets per count of lost balls (seeded: the same answer each time).
Counts of lost balls whose binomial weight is under ``min_weight`` are left out and count as
untrusted (the figure errs low).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

#: subsets of the seen balls tried per count of lost balls when there are more of them
SUBSETS_PER_COUNT = 12


@dataclass(frozen=True)
class LossOutlook:
    """``found_probability``: a seen ball's chance of being found (0..1; with ``found_short`` set,
    that of a ball with skin all round it in the camera's view); ``trusted``: the expected share of
    frames the pose stream trusts, over which balls are found (0..1); ``pose``: the probability
    that the balls found can give a pose at all (enough of them, not collinear or coplanar);
    ``expected_found``: the mean count of balls found; ``subsets``: how many subsets were
    evaluated; ``found_short``: the chance of a seen ball short of skin around it (on the head's
    outline in the camera's view or beside the drape, ``Visibility.short_of_skin``), None when all
    balls were counted alike; ``short_of_skin``: how many of the seen balls are."""

    found_probability: float
    trusted: float
    pose: float
    expected_found: float
    subsets: int
    found_short: float | None = None
    short_of_skin: int = 0

    def to_dict(self) -> dict:
        return {"found_probability": round(self.found_probability, 4), "trusted_fraction": round(self.trusted, 4),
                "pose_probability": round(self.pose, 4), "expected_balls_found": round(self.expected_found, 2),
                "found_probability_short_of_skin": None if self.found_short is None else round(self.found_short, 4),
                "balls_short_of_skin": self.short_of_skin}

    @property
    def phrase(self) -> str:
        """:func:`found_phrase` of this outlook."""
        return found_phrase(self.found_probability, self.found_short, self.short_of_skin)


def found_phrase(found: float, found_short: float | None = None, short_count: int = 0) -> str:
    """How the outlook counted the balls, in words for the plan's notes, the CLI and the app:
    "each ball found at 60 %", and with balls short of skin "(3 on the head's outline or beside
    the drape at 27 %)"."""
    out = f"each ball found at {100 * found:.0f} %"
    if found_short is not None and short_count:
        out += f" ({short_count} on the head's outline or beside the drape at {100 * found_short:.0f} %)"
    return out


def loss_outlook(error_of, seen: np.ndarray, found_probability, *, per_count: int = SUBSETS_PER_COUNT,
                 min_weight: float = 1e-3, seed: int = 0) -> LossOutlook:
    """:class:`LossOutlook` of the balls ``seen`` ((n,) bool) when each is found independently,
    with probability ``found_probability``: one share (0..1) for every ball, or (n,) shares, one
    per ball (module docstring). ``error_of(keep)`` gives the prediction for the balls ``keep``
    ((n,) bool): an object with ``trusted`` (0..1), or None when they give no pose
    (:func:`~.prediction.outlook_with_losses` passes :func:`~.prediction.predict_error`).

    The count of lost balls follows the Poisson-binomial law of the seen balls' shares; within a
    count, every subset when there are at most ``per_count``, each weighted by its probability
    given the count, else ``per_count`` subsets drawn from that conditional law and counted alike
    (:func:`_pick_subsets`; each distinct subset predicted once)."""
    seen = np.asarray(seen, bool)
    q_all = np.broadcast_to(np.asarray(found_probability, float), seen.shape)
    if not np.all((q_all >= 0.0) & (q_all <= 1.0)):
        raise ValueError(f"found probability {found_probability} is not between 0 and 1")
    idx = np.flatnonzero(seen)
    m = len(idx)
    lose = 1.0 - q_all[idx]                       # each seen ball's chance of being lost
    tail = _tail_counts(lose)                     # tail[i, k]: P(exactly k lost among balls i..m-1)
    rng = np.random.default_rng(seed)
    trusted = pose = 0.0
    evaluated = 0
    for lost in range(m + 1):
        w = float(tail[0, lost])
        if w <= 0.0 or w < min_weight:
            continue
        if math.comb(m, lost) <= per_count:       # every subset, weighted by its chance given the count
            subsets = list(itertools.combinations(range(m), lost))
            weights = np.array([_subset_probability(lose, s) for s in subsets])
            weights = weights / weights.sum()
        else:                                     # drawn from the law given the count: equal weights
            subsets = _pick_subsets(lose, tail, lost, per_count, rng)
            weights = np.full(len(subsets), 1.0 / len(subsets))
        t = p = 0.0
        known: dict = {}
        for s, ws in zip(subsets, weights):
            if s not in known:
                keep = seen.copy()
                keep[idx[np.array(s, int)]] = False
                known[s] = error_of(keep)
                evaluated += 1
            e = known[s]
            if e is not None:
                p += ws
                t += ws * float(e.trusted)
        trusted += w * t
        pose += w * p
    q_seen = q_all[idx]
    return LossOutlook(float(q_seen.mean()) if m else float(np.mean(q_all)) if len(q_all) else 0.0,
                       float(trusted), float(pose), float(q_seen.sum()), evaluated)


def _pick_subsets(lose: np.ndarray, tail: np.ndarray, count: int, per_count: int, rng) -> list:
    """``per_count`` subsets (sorted index tuples) of ``count`` lost balls drawn from the law given
    the count, to be counted alike. Equal shares: distinct subsets drawn uniformly (as before per-ball
    shares, so the figures of one share for all stay as they were); unequal shares:
    :func:`_draw_subset` ``per_count`` times, repeats kept (a likelier subset is drawn more often)."""
    m = len(lose)
    if m and float(np.ptp(lose)) > 0.0:
        return [_draw_subset(lose, tail, count, rng) for _ in range(per_count)]
    picked: set = set()
    while len(picked) < per_count:
        picked.add(tuple(sorted(rng.choice(m, size=count, replace=False).tolist())))
    return sorted(picked)


def _tail_counts(lose: np.ndarray) -> np.ndarray:
    """(m + 1, m + 1): ``[i, k]`` the probability that exactly ``k`` of balls ``i..m-1`` are lost,
    each independently with its share ``lose[j]`` (row 0: the Poisson-binomial law of the count)."""
    m = len(lose)
    tail = np.zeros((m + 1, m + 1))
    tail[m, 0] = 1.0
    for i in range(m - 1, -1, -1):
        tail[i] = (1.0 - lose[i]) * tail[i + 1]
        tail[i, 1:] += lose[i] * tail[i + 1, :-1]
    return tail


def _draw_subset(lose: np.ndarray, tail: np.ndarray, count: int, rng) -> tuple:
    """One subset of ``count`` lost balls (indices into ``lose``), drawn from the law of which
    balls are lost given that ``count`` are: ball by ball, lost with its share times the chance
    that the rest then lose the remaining count, over the chance of that count from here."""
    out, k = [], count
    for i in range(len(lose)):
        if k == 0:
            break
        if len(lose) - i == k:            # every ball left must be lost (also guards rounding)
            out.extend(range(i, len(lose)))
            break
        p = lose[i] * tail[i + 1, k - 1] / tail[i, k] if tail[i, k] > 0.0 else 0.0
        if rng.random() < p:
            out.append(i)
            k -= 1
    return tuple(out)


def _subset_probability(lose: np.ndarray, s: np.ndarray) -> float:
    """The probability that exactly the balls ``s`` (indices into ``lose``) are lost."""
    mask = np.zeros(len(lose), bool)
    mask[np.asarray(s, int)] = True
    return float(np.prod(lose[mask]) * np.prod(1.0 - lose[~mask]))
