"""An operator-added fiducial is verified only where the CT holds a ball (issue 36: a point
inside the skull passed the old mean-contrast check as a "verified ball").

Truth is the analytic phantom: its balls' centres, and points in the middle of its 7 mm skull
shell (under the scalp's 5 mm) or in the brain."""

from __future__ import annotations

import numpy as np
import pytest
from ct_test_helpers import patch_params

from monotracker.ct.ball_check import check_ball_at
from monotracker.ct.levels import estimate_levels
from monotracker.ct.volume import Volume
from monotracker.sim.ct_phantom import generate_ct
from monotracker.sim.phantom import default_phantom


@pytest.fixture(scope="module")
def patch_volume():
    """The fiducial patch with 22 mm around the balls: the skull and brain under them too."""
    ct = generate_ct(default_phantom(), patch_params(margin_mm=22.0, spacing_mm=(0.7, 0.7, 1.0)))
    return Volume.from_image(ct.to_sitk(), source="patch")


@pytest.fixture(scope="module")
def levels(patch_volume):
    return estimate_levels(patch_volume)


def test_every_ball_of_the_phantom_is_verified_at_its_centre(patch_volume, levels):
    ph = default_phantom()
    for c in ph.fiducial_centres_lps:
        res = check_ball_at(patch_volume, c + [0.6, -0.4, 0.3], ph.fiducial_radius_mm, levels)
        assert res.verified, res.why
        assert np.linalg.norm(res.centre_lps - c) < 0.1


def test_points_inside_the_skull_are_not_balls(patch_volume, levels):
    ph = default_phantom()
    for c in ph.fiducial_centres_lps:
        # the middle of the skull shell under the ball: 5 mm scalp + 3.5 mm into the 7 mm skull
        p, _ = ph.skin_point(c - ph.centre_lps, inset_mm=8.5)
        res = check_ball_at(patch_volume, p, ph.fiducial_radius_mm, levels)
        assert not res.verified, (p, res.why)
        assert "bone" in res.why or "no fiducial ball" in res.why or "no dense ball" in res.why, res.why


def test_a_point_in_the_brain_or_beside_a_ball_is_not_a_ball(patch_volume, levels):
    ph = default_phantom()
    c = ph.fiducial_centres_lps[0]
    p, _ = ph.skin_point(c - ph.centre_lps, inset_mm=25.0)
    res = check_ball_at(patch_volume, p, ph.fiducial_radius_mm, levels)
    assert not res.verified and "no dense ball" in res.why, res.why
    res = check_ball_at(patch_volume, c, 2.0, levels)  # the wrong size
    assert not res.verified and "radius" in res.why, res.why
