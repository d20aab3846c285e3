"""The analytic head phantom: the one geometric truth shared by the synthetic CT, the simulated
camera, the tests, the benchmarks and the demo.

Everything here is in the CT's physical frame: LPS millimetres (x to the patient's Left, y to
Posterior, z to Superior), as SimpleITK and DICOM report CT points.

Geometry (choices written down because the paper leaves them open):

* Skin: an axis-aligned ellipsoid (semi-axes 72 x 92 x 86 mm, an adult head), cut below by a
  horizontal neck plane. Scalp 5 mm thick, then a 7 mm skull shell, brain inside.
* Fiducials: 9 spheres of radius 4.0 mm (8 mm balls) resting on the scalp (centre = skin point
  + radius along the outward normal), all on the right-anterior-superior patch that one camera
  sees, placed irregularly so that no two configurations look alike. Indices 0-4 are the
  registration set, 5-8 the validation set (the paper's 5 + 4).
  Material: alumina ceramic (Al2O3, ~3.9 g/cm^3), modelled at 3000 HU. That is far denser
  than skull (cortical bone ~1000-1900 HU, 1200 HU here) so a grey-value threshold separates
  it, yet unlike steel it does not throw streak artefacts. For the camera the balls are
  matte-dyed green, a colour that skin, drapes and gloves do not have.
* A skin clip (a small steel-density cylinder) sits on the scalp as a realistic distractor
  that a fiducial detector must reject: dense like a fiducial, but not a sphere.
* A sample puncture plan: entry on the skin inside the fiducial patch, target deep in the
  right hemisphere (a typical haematoma-drainage trajectory), ~70 mm long.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Tissue values in Hounsfield units used by the synthetic CT.
HU = {
    "air": -1000.0,
    "scalp": 40.0,
    "bone": 1200.0,
    "brain": 35.0,
    "fiducial": 3000.0,
    "clip": 3000.0,
}


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _tangent_frame(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to ``d`` and each other (deterministic)."""
    helper = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = _unit(np.cross(d, helper))
    e2 = np.cross(d, e1)
    return e1, e2


def _direction(view: np.ndarray, theta_deg: float, phi_deg: float) -> np.ndarray:
    """Unit direction at polar angle ``theta`` from ``view``, azimuth ``phi`` around it."""
    e1, e2 = _tangent_frame(view)
    th, ph = np.radians(theta_deg), np.radians(phi_deg)
    return _unit(np.cos(th) * view + np.sin(th) * (np.cos(ph) * e1 + np.sin(ph) * e2))


# (polar angle from the view direction, azimuth) of each fiducial, degrees. Irregular on purpose.
_FIDUCIAL_ANGLES_DEG = (
    (8.0, 20.0),
    (28.0, 75.0),
    (35.0, 150.0),
    (30.0, 215.0),
    (40.0, 290.0),
    (18.0, 330.0),
    (45.0, 20.0),
    (22.0, 250.0),
    (42.0, 110.0),
)


@dataclass(frozen=True)
class HeadPhantom:
    """Analytic head phantom in CT LPS millimetres. See the module docstring."""

    centre_lps: np.ndarray = field(default_factory=lambda: np.array([4.0, -12.0, 38.0]))
    skin_semi_axes_mm: np.ndarray = field(default_factory=lambda: np.array([72.0, 92.0, 86.0]))
    scalp_thickness_mm: float = 5.0
    skull_thickness_mm: float = 7.0
    #: Nothing exists below this z (mm, LPS): the neck cut, 55 mm below the head centre.
    neck_cut_below_centre_mm: float = 55.0
    fiducial_radius_mm: float = 4.0
    #: Direction (LPS, unit) from the head centre towards the fiducial patch and the camera:
    #: right (-x), anterior (-y), superior (+z).
    view_direction_lps: np.ndarray = field(default_factory=lambda: _unit([-0.45, -0.35, 0.82]))
    fiducial_angles_deg: tuple = _FIDUCIAL_ANGLES_DEG
    registration_ids: tuple = (0, 1, 2, 3, 4)
    validation_ids: tuple = (5, 6, 7, 8)
    clip_length_mm: float = 10.0
    clip_radius_mm: float = 0.8

    # ----------------------------------------------------------------- skin geometry
    def skin_point(self, direction: np.ndarray, inset_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Point where the ray from the head centre along ``direction`` meets the skin
        ellipsoid shrunk by ``inset_mm`` on every semi-axis, and the outward unit normal there."""
        u = _unit(direction)
        axes = self.skin_semi_axes_mm - inset_mm
        t = 1.0 / np.sqrt(np.sum(u**2 / axes**2))
        p = self.centre_lps + t * u
        n = _unit((p - self.centre_lps) / axes**2)
        return p, n

    @property
    def neck_cut_z_mm(self) -> float:
        return float(self.centre_lps[2] - self.neck_cut_below_centre_mm)

    # ----------------------------------------------------------------- fiducials
    @property
    def fiducial_centres_lps(self) -> np.ndarray:
        """(9, 3) true sphere centres, LPS mm."""
        out = []
        for theta, phi in self.fiducial_angles_deg:
            p, n = self.skin_point(_direction(self.view_direction_lps, theta, phi))
            out.append(p + self.fiducial_radius_mm * n)
        return np.array(out)

    def with_fiducials_at(self, centres_lps: np.ndarray) -> "HeadPhantom":
        """This phantom with its balls moved to ``centres_lps`` (n, 3) LPS mm (a planned layout):
        each ball rests on the skin (its centre one radius out along the skin's normal) where its
        centre comes nearest the given one: a centre that already rests on the skin stays where it
        is (to ~1e-6 mm), so placing a placed layout again moves nothing; all of them in the
        registration set. The clip and the sample plan stay. (Before, the ball went along the
        direction from the head's centre, which moved a resting ball by up to 1 mm each time.)"""
        from dataclasses import replace

        v = self.view_direction_lps
        e1, e2 = _tangent_frame(v)
        angles = []
        r = self.fiducial_radius_mm
        for c in np.asarray(centres_lps, float).reshape(-1, 3):
            u = _unit(c - self.centre_lps)
            for _ in range(50):          # move the skin point by what the resting centre misses
                p, n = self.skin_point(u)
                miss = c - (p + r * n)
                if np.linalg.norm(miss) < 1e-7:
                    break
                u = _unit(p + miss - self.centre_lps)
            theta = float(np.degrees(np.arccos(np.clip(u @ v, -1.0, 1.0))))
            phi = float(np.degrees(np.arctan2(u @ e2, u @ e1)))
            angles.append((theta, phi))
        n = len(angles)
        return replace(self, fiducial_angles_deg=tuple(angles), registration_ids=tuple(range(n)), validation_ids=())

    @property
    def fiducial_count(self) -> int:
        return len(self.fiducial_angles_deg)

    # ----------------------------------------------------------------- distractor
    @property
    def clip_segment_lps(self) -> tuple[np.ndarray, np.ndarray]:
        """End points (LPS mm) of the skin clip's axis, lying on the scalp."""
        p, n = self.skin_point(_direction(self.view_direction_lps, 36.0, 185.0))
        e1, _ = _tangent_frame(n)
        c = p + (self.clip_radius_mm + 0.2) * n
        return c - 0.5 * self.clip_length_mm * e1, c + 0.5 * self.clip_length_mm * e1

    # ----------------------------------------------------------------- sample plan
    @property
    def sample_entry_lps(self) -> np.ndarray:
        """Planned entry point on the skin (LPS mm), inside the fiducial patch."""
        p, _ = self.skin_point(_direction(self.view_direction_lps, 14.0, 175.0))
        return p

    @property
    def sample_target_lps(self) -> np.ndarray:
        """Planned deep target (LPS mm): right basal-ganglia region."""
        return self.centre_lps + np.array([-22.0, -8.0, 8.0])

    def summary(self) -> dict:
        """JSON-ready ground truth (LPS mm)."""
        a, b = self.clip_segment_lps
        return {
            "frame": "LPS",
            "units": "mm",
            "fiducial_radius_mm": self.fiducial_radius_mm,
            "fiducial_centres_lps_mm": self.fiducial_centres_lps.round(6).tolist(),
            "registration_ids": list(self.registration_ids),
            "validation_ids": list(self.validation_ids),
            "head_centre_lps_mm": self.centre_lps.tolist(),
            "skin_semi_axes_mm": self.skin_semi_axes_mm.tolist(),
            "neck_cut_z_mm": self.neck_cut_z_mm,
            "clip_segment_lps_mm": [a.round(6).tolist(), b.round(6).tolist()],
            "sample_entry_lps_mm": self.sample_entry_lps.round(6).tolist(),
            "sample_target_lps_mm": self.sample_target_lps.round(6).tolist(),
        }


def default_phantom() -> HeadPhantom:
    """The phantom behind ``sample_data/`` and the default simulated camera."""
    return HeadPhantom()
