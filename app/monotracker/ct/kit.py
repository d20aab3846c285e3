"""The fiducial kit: what the balls on the patient's head are, as far as the operator knows.

Kept in the plan (``Plan.fiducial_kit``) so the CT is searched for the balls actually used.
Both fields are optional: without a radius it is estimated from the balls (their median), without
a density the search covers everything from a little above soft tissue up to the densest voxels.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class FiducialKit:
    """Nominal ball radius (mm) and material density (HU, e.g. ceramic 1500-2000, steel/titanium
    saturating at 3071), ``None`` where unknown; ``name`` is free text for the record."""

    radius_mm: float | None = None
    density_hu: float | None = None
    name: str = ""

    def __post_init__(self):
        if self.radius_mm is not None and not (0.5 <= float(self.radius_mm) <= 20.0):
            raise ValueError(f"fiducial radius {self.radius_mm} mm is implausible (0.5-20 mm)")
        if self.density_hu is not None and not (300.0 <= float(self.density_hu) <= 30000.0):
            raise ValueError(f"fiducial density {self.density_hu} HU is implausible (300-30000 HU, denser than soft tissue)")

    def to_dict(self) -> dict:
        return {"radius_mm": self.radius_mm, "density_hu": self.density_hu, "name": self.name}

    @classmethod
    def from_dict(cls, d: dict | None) -> "FiducialKit | None":
        """Parse a saved kit (None stays None); ``ValueError`` with a one-line reason if malformed."""
        if d is None:
            return None
        if not isinstance(d, dict):
            raise ValueError("fiducial kit is not a mapping")

        def num(key):
            v = d.get(key)
            return None if v is None else float(v)

        return cls(num("radius_mm"), num("density_hu"), str(d.get("name", "") or ""))
