"""The surgical plan: what must survive a crash.

A :class:`Plan` holds the CT it was made on, the fiducials (with the operator's decisions), whether
the fiducial set is locked, the planned path (entry and target, CT LPS mm), the camera source and
calibration (K px, distortion, image size) and the hand-eye transform ``T_base_cam`` (mm). It is
saved as JSON with :func:`monotracker.engine.persistence.atomic_write_json` after every change, and
loaded at start-up. It is plain data: the session validates changes, the plan only stores them.

Format: ``{"format": "monotracker-plan", "version": 1, ...}``; arrays as nested lists. The
``"integrity"`` object records SHA-256 hashes of the CT and calibration the plan was made with and
of the plan's own content (:mod:`monotracker.engine.integrity`), so an edit made outside the app
or a changed CT is noticed at restore.

Restoring runs the same checks as the commands (:mod:`~monotracker.engine.plan.checks`), field by
field (:func:`~monotracker.engine.plan.store.restore_plan`); :func:`~monotracker.engine.plan.store.plan_from_dict`
is the strict form that refuses the first invalid field. This module is the model only: it
imports neither the checks nor the store (model <- checks <- store <- editor).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monotracker.engine.persistence import atomic_write_json

FORMAT = "monotracker-plan"
VERSION = 1
STATUSES = ("detected", "confirmed", "rejected", "added")
#: "registration": used in the fit; "validation": seen by the camera but left out of the fit, to
#: verify the registration independently (``registration.validation``)
ROLES = ("registration", "validation")


@dataclass
class PlanFiducial:
    """A CT fiducial: ``centre_lps_mm`` (3,) LPS mm, ``radius_mm``, detector ``score`` (0..1,
    1.0 for operator-added), ``status`` one of :data:`STATUSES`. ``verified``: for an operator-added
    fiducial, True when the CT shows a dense ball of its radius there, False when it was added
    manually without that ("manual, unverified"), None for detected ones."""

    id: int
    centre_lps_mm: np.ndarray
    radius_mm: float
    score: float
    status: str = "detected"
    verified: bool | None = None
    role: str = "registration"  # one of ROLES

    @property
    def usable(self) -> bool:
        """Counts for registration: confirmed by the operator or added by them."""
        return self.status in ("confirmed", "added")


@dataclass
class Plan:
    ct_path: str | None = None
    fiducials: list[PlanFiducial] = field(default_factory=list)
    fiducials_locked: bool = False
    entry_lps_mm: np.ndarray | None = None
    target_lps_mm: np.ndarray | None = None
    camera_source: str | None = None
    calibration_path: str | None = None
    K: np.ndarray | None = None
    dist: np.ndarray | None = None
    image_size: tuple | None = None
    T_base_cam: np.ndarray | None = None
    #: The balls used (``monotracker.ct.FiducialKit``: radius mm, density HU) or None (estimated).
    fiducial_kit: "object | None" = None
    #: What the team says of the kit's balls' finish for this patient: "read" (each frame's
    #: highlight decides), "matte" or "glossy" (vision's ``TrackerConfig.ball_finish``,
    #: :data:`monotracker.vision.ball_gloss.FINISHES`), or None: the session's launch setting
    #: (``SessionConfig.ball_finish``, ``serve --ball-finish``).
    ball_finish: str | None = None
    revision: int = 0
    #: hashes recorded with the plan: ``ct_sha256``, ``calibration_sha256`` (None: not known)
    integrity: dict = field(default_factory=dict)

    # ------------------------------------------------------------------ queries
    def usable_fiducials(self) -> list[PlanFiducial]:
        return [f for f in self.fiducials if f.usable]

    def registration_fiducials(self) -> list[PlanFiducial]:
        """Usable fiducials the registration fits (role "registration"), in id order."""
        return [f for f in self.usable_fiducials() if f.role == "registration"]

    def validation_fiducials(self) -> list[PlanFiducial]:
        """Usable fiducials kept out of the fit to verify it (role "validation")."""
        return [f for f in self.usable_fiducials() if f.role == "validation"]

    def registration_centres(self) -> np.ndarray:
        """(n, 3) LPS mm of the registration fiducials, in id order."""
        return np.array([f.centre_lps_mm for f in self.registration_fiducials()], dtype=float).reshape(-1, 3)

    def fiducial_centres(self) -> np.ndarray:
        """(n, 3) LPS mm of the usable fiducials, in id order."""
        fs = self.usable_fiducials()
        return np.array([f.centre_lps_mm for f in fs], dtype=float).reshape(-1, 3)

    def fiducial(self, fid: int) -> PlanFiducial | None:
        return next((f for f in self.fiducials if f.id == fid), None)

    @property
    def path_complete(self) -> bool:
        return self.entry_lps_mm is not None and self.target_lps_mm is not None

    def copy(self) -> "Plan":
        return copy.deepcopy(self)

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict:
        def arr(a):
            return None if a is None else np.asarray(a, dtype=float).tolist()

        from monotracker.engine.integrity import stamp_plan_dict

        return stamp_plan_dict({
            "format": FORMAT,
            "version": VERSION,
            "revision": self.revision,
            "frame": "LPS",
            "units": "mm",
            "ct_path": self.ct_path,
            "fiducials": [
                {"id": f.id, "centre_lps_mm": arr(f.centre_lps_mm), "radius_mm": float(f.radius_mm),
                 "score": float(f.score), "status": f.status, "verified": f.verified,
                 "role": f.role}
                for f in self.fiducials
            ],
            "fiducials_locked": bool(self.fiducials_locked),
            "entry_lps_mm": arr(self.entry_lps_mm),
            "target_lps_mm": arr(self.target_lps_mm),
            "camera": {
                "source": self.camera_source,
                "calibration_path": self.calibration_path,
                "K": arr(self.K),
                "dist": arr(self.dist),
                "image_size": None if self.image_size is None else list(self.image_size),
            },
            "T_base_cam_mm": arr(self.T_base_cam),
            "fiducial_kit": None if self.fiducial_kit is None else self.fiducial_kit.to_dict(),
            "ball_finish": self.ball_finish,
            "integrity": {k: v for k, v in sorted(self.integrity.items()) if k != "plan_sha256"},
        })

    def save(self, path: Path) -> None:
        """Atomic, durable save (temp file, fsync, rename)."""
        atomic_write_json(path, self.to_dict())


# ---------------------------------------------------------------------- plan metrics
def path_length_mm(entry: np.ndarray, target: np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(target, float) - np.asarray(entry, float)))


def distance_segment_to_points_mm(a: np.ndarray, b: np.ndarray, points: np.ndarray) -> float | None:
    """Smallest distance (mm) from segment a-b to any of ``points`` (n, 3); None if no points."""
    pts = np.asarray(points, float).reshape(-1, 3)
    if len(pts) == 0:
        return None
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    L2 = float(ab @ ab)
    s = np.zeros(len(pts)) if L2 == 0 else np.clip((pts - a) @ ab / L2, 0.0, 1.0)
    closest = a + s[:, None] * ab
    return float(np.min(np.linalg.norm(pts - closest, axis=1)))


def angle_to_skin_normal_deg(entry: np.ndarray, target: np.ndarray, vertices: np.ndarray,
                             vertex_normals: np.ndarray) -> float | None:
    """Angle (deg) between the outward skin normal at the entry (normal of the nearest surface
    vertex) and the direction target -> entry; 0 means the needle enters perpendicular to the
    skin. None when there is no surface."""
    if vertices is None or len(vertices) == 0:
        return None
    entry, target = np.asarray(entry, float), np.asarray(target, float)
    i = int(np.argmin(np.linalg.norm(vertices - entry, axis=1)))
    n = np.asarray(vertex_normals[i], float)
    d = entry - target
    nd = np.linalg.norm(d) * np.linalg.norm(n)
    if nd == 0:
        return None
    return float(np.degrees(np.arccos(np.clip(float(n @ d) / nd, -1.0, 1.0))))
