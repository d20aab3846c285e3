"""Candidate ball positions on the skin, and which of them the rules allow.

A candidate is a place a ball could sit: a skin point (a vertex of the head mesh, thinned to one
per ``spacing_mm`` cell), its outward normal, and the ball centre ``skin + radius * normal``
(LPS mm). The fiducials the CT already has are candidates too (where they are); skin within a
ball's reach of one of them is not sampled (the mesh wraps the ball there, so its normal lies).

Each candidate carries why it is not allowed ('' when it is): under the drape, too near the
incision or the path, outside the surgeon's region. Separation between chosen balls is the
search's business (it depends on the other balls).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .problem import PlanningProblem

#: default spacing of the candidate grid on the skin (mm): a ball is 8-10 mm across, so 6 mm
#: leaves no gap a ball could use and keeps ~1000-2500 candidates on a head
DEFAULT_SPACING_MM = 6.0


@dataclass(frozen=True)
class Candidates:
    """``centres`` (n, 3) ball centres, ``skin`` (n, 3) skin points, ``normals`` (n, 3) outward
    unit normals (LPS mm); ``existing`` (n,) int: index of the CT fiducial this candidate is, -1
    for a new position; ``why_not`` n strings, '' where a new ball is allowed."""

    centres: np.ndarray
    skin: np.ndarray
    normals: np.ndarray
    existing: np.ndarray
    why_not: tuple

    def __len__(self) -> int:
        return len(self.centres)

    @property
    def allowed(self) -> np.ndarray:
        """(n,) bool: the rules allow a ball here."""
        return np.array([w == "" for w in self.why_not], bool)


def _thin(points: np.ndarray, spacing_mm: float) -> np.ndarray:
    """Indices of one point per cubic cell of ``spacing_mm`` (the one nearest the cell's centre)."""
    cell = np.floor(points / spacing_mm).astype(np.int64)
    centre = (cell + 0.5) * spacing_mm
    d = np.linalg.norm(points - centre, axis=1)
    order = np.lexsort((d, cell[:, 2], cell[:, 1], cell[:, 0]))
    c = cell[order]
    first = np.ones(len(order), bool)
    first[1:] = np.any(c[1:] != c[:-1], axis=1)
    return np.sort(order[first])


def _path_distance(problem: PlanningProblem, points: np.ndarray) -> np.ndarray | None:
    """(n,) distance (mm) from points to the path's line (target -> entry, extended outwards)."""
    if problem.entry is None:
        return None
    from .problem import Capsule

    out = problem.entry - problem.target
    out = out / np.linalg.norm(out)
    line = Capsule(problem.target, problem.entry + problem.rules.path_extension_mm * out, 1.0, "path")
    return line.distance(points)


def why_not_allowed(problem: PlanningProblem, centres: np.ndarray) -> list[str]:
    """One string per ball centre (n, 3) LPS mm: '' where the rules allow a ball, else why not."""
    c = np.asarray(centres, float).reshape(-1, 3)
    r = problem.rules
    out = [""] * len(c)
    reasons = []
    if problem.drape is not None:
        reasons.append((problem.drape.covers(c), "under the drape"))
    if problem.entry is not None:
        reasons.append((np.linalg.norm(c - problem.entry, axis=1) < r.incision_clearance_mm + problem.radius_mm,
                        "too near the incision"))
        reasons.append((_path_distance(problem, c) < r.path_clearance_mm + problem.radius_mm, "too near the path"))
    if r.region_axis is not None:
        u = c - problem.head.centre
        cosang = (u @ r.region_axis) / np.maximum(np.linalg.norm(u, axis=1), 1e-9)
        reasons.append((cosang < np.cos(np.radians(r.region_half_angle_deg)), "outside the allowed region"))
    for mask, why in reasons:
        for i in np.flatnonzero(mask):
            if not out[i]:
                out[i] = why
    return out


def sample_candidates(problem: PlanningProblem, spacing_mm: float = DEFAULT_SPACING_MM) -> Candidates:
    """The candidate positions of ``problem`` (see the module docstring), existing fiducials first."""
    head, rad = problem.head, problem.radius_mm
    idx = _thin(head.vertices, float(spacing_mm))
    skin, normals = head.vertices[idx], head.normals[idx]
    ok = np.linalg.norm(normals, axis=1) > 0.5
    skin, normals = skin[ok], normals[ok] / np.linalg.norm(normals[ok], axis=1, keepdims=True)
    ex = problem.existing
    if len(ex):
        # skin wrapped around an existing ball: its normals point anywhere; the ball itself is a candidate
        near = np.min(np.linalg.norm(skin[:, None, :] - ex[None], axis=2), axis=1) < 2.0 * rad + 2.0
        skin, normals = skin[~near], normals[~near]
        ex_normals = skin_normals_under(head, ex, rad)
        skin = np.vstack([ex - rad * ex_normals, skin])
        normals = np.vstack([ex_normals, normals])
    centres = skin + rad * normals
    existing = np.concatenate([np.arange(len(ex)), np.full(len(centres) - len(ex), -1)]).astype(int)
    return Candidates(centres, skin, normals, existing, tuple(why_not_allowed(problem, centres)))


def skin_normals_under(head, centres: np.ndarray, radius_mm: float) -> np.ndarray:
    """(n, 3) outward skin normals under balls at ``centres`` (n, 3) LPS mm: the mean vertex
    normal of the skin in a ring around each ball (where a ball is in the CT the mesh wraps it,
    so the normals right under it are the ball's, not the skin's)."""
    out = []
    for c in np.asarray(centres, float).reshape(-1, 3):
        d = np.linalg.norm(head.vertices - c, axis=1)
        ring = (d > 2.0 * radius_mm + 2.0) & (d < 2.0 * radius_mm + 10.0)
        n = head.normals[ring].sum(axis=0) if np.any(ring) else c - head.centre
        out.append(n / np.linalg.norm(n))
    return np.array(out).reshape(-1, 3)
