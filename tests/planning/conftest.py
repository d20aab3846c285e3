"""Shared fixtures of the layout-planner tests: an analytic head (the phantom's skin ellipsoid as
a mesh), a plan on it and a camera space, built once per session (CT-free: fast)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from monotracker.planning import BallRules, CameraSpace, DrapeLine, HeadSurface, PlanningProblem, robot_keep_out
from monotracker.sim.phantom import default_phantom
from monotracker.vision.camera_model import default_camera

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


@pytest.fixture(scope="session")
def head():
    return ellipsoid_head()


@pytest.fixture(scope="session")
def problem(head):
    """The sample plan on the analytic head: camera cone of 30 deg around the phantom's view
    direction, 400-600 mm; drape through the head's centre; the robot along the path."""
    v = PH.view_direction_lps
    entry, target = PH.sample_entry_lps, PH.sample_target_lps
    space = CameraSpace(v, 30.0, (400.0, 600.0), keep_out=robot_keep_out(entry, target))
    return PlanningProblem(head=head, target=target, camera=default_camera(), space=space, entry=entry,
                           radius_mm=4.0, noise_px=0.2, drape=DrapeLine(PH.centre_lps, v), rules=BallRules(),
                           existing=PH.fiducial_centres_lps)
