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
    """``found_probability``: each seen ball's chance of being found (0..1); ``trusted``: the
    expected share of frames the pose stream trusts, over which balls are found (0..1);
    ``pose``: the probability that the balls found can give a pose at all (enough of them, not
    collinear or coplanar); ``expected_found``: the mean count of balls found; ``subsets``: how
    many subsets were evaluated."""

    found_probability: float
    trusted: float
    pose: float
    expected_found: float
    subsets: int

    def to_dict(self) -> dict:
        return {"found_probability": round(self.found_probability, 4), "trusted_fraction": round(self.trusted, 4),
                "pose_probability": round(self.pose, 4), "expected_balls_found": round(self.expected_found, 2)}


def loss_outlook(error_of, seen: np.ndarray, found_probability: float, *, per_count: int = SUBSETS_PER_COUNT,
                 min_weight: float = 1e-3, seed: int = 0) -> LossOutlook:
    """:class:`LossOutlook` of the balls ``seen`` ((n,) bool) when each is found with probability
    ``found_probability`` (module docstring). ``error_of(keep)`` gives the prediction for the balls
    ``keep`` ((n,) bool): an object with ``trusted`` (0..1), or None when they give no pose
    (:func:`~.prediction.outlook_with_losses` passes :func:`~.prediction.predict_error`)."""
    q = float(found_probability)
    if not (0.0 <= q <= 1.0):
        raise ValueError(f"found probability {q} is not between 0 and 1")
    seen = np.asarray(seen, bool)
    idx = np.flatnonzero(seen)
    m = len(idx)
    rng = np.random.default_rng(seed)
    trusted = pose = 0.0
    evaluated = 0
    for lost in range(m + 1):
        w = math.comb(m, lost) * q ** (m - lost) * (1.0 - q) ** lost
        if w < min_weight:
            continue
        if math.comb(m, lost) <= per_count:
            subsets = [np.array(s, int) for s in itertools.combinations(range(m), lost)]
        else:
            picked: set = set()
            while len(picked) < per_count:
                picked.add(tuple(sorted(rng.choice(m, size=lost, replace=False).tolist())))
            subsets = [np.array(s, int) for s in sorted(picked)]
        t = p = 0.0
        for s in subsets:
            keep = seen.copy()
            keep[idx[s]] = False
            e = error_of(keep)
            evaluated += 1
            if e is not None:
                p += 1.0
                t += float(e.trusted)
        trusted += w * t / len(subsets)
        pose += w * p / len(subsets)
    return LossOutlook(q, float(trusted), float(pose), q * m, evaluated)
