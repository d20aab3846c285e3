"""The analytic head of the layout-planner tests: the phantom's skin ellipsoid as a mesh and balls
resting on it (CT-free). A module of its own, not conftest.py, so a test can import it by a name no
other test folder uses (``from conftest import ...`` picks whichever conftest pytest loaded last)."""

from __future__ import annotations

import numpy as np
import trimesh

from monotracker.planning import HeadSurface
from monotracker.sim.phantom import default_phantom

PH = default_phantom()


def ellipsoid_head(subdivisions: int = 5) -> HeadSurface:
    """The phantom's skin ellipsoid (LPS mm, semi-axes 72 x 92 x 86) as a closed mesh."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = np.asarray(m.vertices) * PH.skin_semi_axes_mm + PH.centre_lps
    return HeadSurface(v, np.asarray(m.faces))


def skin_ball(direction, radius_mm: float = 4.0) -> np.ndarray:
    """A ball centre resting on the phantom's skin along ``direction`` from its centre (LPS mm)."""
    p, n = PH.skin_point(np.asarray(direction, float))
    return p + radius_mm * n
