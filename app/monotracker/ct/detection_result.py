"""What a CT fiducial detection returns: the balls found (LPS mm) and the dense blobs rejected,
each with its reason (:mod:`monotracker.ct.fiducials`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Fiducial:
    """One detected ball: centre (LPS mm), fitted radius (mm), score in [0, 1]."""

    centre_lps: np.ndarray
    radius_mm: float
    score: float
    peak_hu: float = float("nan")
    n_voxels: int = 0
    elongation: float = 1.0
    fit_residual: float = 0.0

    def to_dict(self) -> dict:
        return {
            "centre_lps_mm": [round(float(x), 4) for x in self.centre_lps],
            "radius_mm": round(float(self.radius_mm), 3),
            "score": round(float(self.score), 3),
            "peak_hu": round(float(self.peak_hu), 1),
            "n_voxels": int(self.n_voxels),
        }


@dataclass
class RejectedBlob:
    """A dense blob that is not taken as a fiducial, and why."""

    centre_lps: np.ndarray
    reason: str
    n_voxels: int = 0
    radius_mm: float = float("nan")
    #: What kind of refusal, for code that acts on it: "" (other), "round" (a ball of another
    #: size than searched for), "wrong_size" (fitted ball, radius off), "cut" (cut by the edge
    #: of the scan or by missing slices).
    kind: str = ""

    def to_dict(self) -> dict:
        return {
            "centre_lps_mm": [round(float(x), 3) for x in self.centre_lps],
            "reason": self.reason,
            "n_voxels": int(self.n_voxels),
            "radius_mm": None if not np.isfinite(self.radius_mm) else round(float(self.radius_mm), 3),
        }


@dataclass
class FiducialDetection:
    """Result of a detection. ``centres`` is (n, 3) LPS mm in the order of ``fiducials``."""

    ok: bool
    reason: str
    fiducials: list[Fiducial] = field(default_factory=list)
    rejected: list[RejectedBlob] = field(default_factory=list)
    threshold_hu: float = float("nan")
    levels: dict = field(default_factory=dict)
    method: str = "robust"
    elapsed_s: float = 0.0
    notes: list[str] = field(default_factory=list)
    #: The threshold ladder searched, HU (ascending); ``threshold_hu`` is its lowest level.
    thresholds_hu: list[float] = field(default_factory=list)

    @property
    def centres(self) -> np.ndarray:
        if not self.fiducials:
            return np.zeros((0, 3))
        return np.array([f.centre_lps for f in self.fiducials], float)

    @property
    def radii_mm(self) -> np.ndarray:
        return np.array([f.radius_mm for f in self.fiducials], float)

    def to_dict(self) -> dict:
        return {
            "ok": self.ok,
            "reason": self.reason,
            "method": self.method,
            "frame": "LPS",
            "units": "mm",
            "threshold_hu": None if not np.isfinite(self.threshold_hu) else round(float(self.threshold_hu), 1),
            "thresholds_hu": [round(float(t), 1) for t in self.thresholds_hu],
            "levels_hu": {k: round(float(v), 1) for k, v in self.levels.items()},
            "fiducials": [f.to_dict() for f in self.fiducials],
            "rejected": [r.to_dict() for r in self.rejected],
            "elapsed_s": round(self.elapsed_s, 4),
            "notes": list(self.notes),
        }
