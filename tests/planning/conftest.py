"""Shared fixtures of the layout-planner tests: an analytic head (the phantom's skin ellipsoid as
a mesh), a plan on it and a camera space, built once per session (CT-free: fast)."""

from __future__ import annotations

import pytest
from analytic_head import PH, ellipsoid_head

from monotracker.planning import BallRules, CameraSpace, DrapeLine, PlanningProblem, robot_keep_out
from monotracker.vision.camera_model import default_camera


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
