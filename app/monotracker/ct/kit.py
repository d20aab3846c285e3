"""The fiducial kit: what the balls on the patient's head are, as far as the operator knows.

Kept in the plan (``Plan.fiducial_kit``) so the CT is searched for the balls actually used.
Both fields are optional: without a radius it is estimated from the balls (their median), without
a density the search covers everything from a little above soft tissue up to the densest voxels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Plausible nominal ball radius, mm (every check of a kit uses these).
RADIUS_MM = (0.5, 20.0)
#: Plausible ball density, HU: denser than soft tissue; up to extended-range scanners.
DENSITY_HU = (300.0, 30000.0)


@dataclass(frozen=True)
class FiducialKit:
    """Nominal ball radius (mm) and material density (HU, e.g. ceramic 1500-2000, steel/titanium
    saturating at 3071), ``None`` where unknown; ``name`` is free text for the record."""

    radius_mm: float | None = None
    density_hu: float | None = None
    name: str = ""

    def __post_init__(self):
        for what, v in (("radius", self.radius_mm), ("density", self.density_hu)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating))):
                raise ValueError(f"fiducial {what} must be a number, not {v!r}")
            if v is not None and not np.isfinite(float(v)):
                raise ValueError(f"fiducial {what} must be a finite number, not {v!r}")
        if self.radius_mm is not None and not (RADIUS_MM[0] <= float(self.radius_mm) <= RADIUS_MM[1]):
            raise ValueError(f"fiducial radius {self.radius_mm} mm is implausible ({RADIUS_MM[0]:g}-{RADIUS_MM[1]:g} mm)")
        if self.density_hu is not None and not (DENSITY_HU[0] <= float(self.density_hu) <= DENSITY_HU[1]):
            raise ValueError(f"fiducial density {self.density_hu} HU is implausible "
                             f"({DENSITY_HU[0]:g}-{DENSITY_HU[1]:g} HU, denser than soft tissue)")

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
            if v is None:
                return None
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ValueError(f"fiducial kit {key} must be a number, not {v!r}")
            return float(v)

        return cls(num("radius_mm"), num("density_hu"), str(d.get("name", "") or ""))
