"""The analytic phantom's own invariants, checked against the ellipsoid equation."""

import numpy as np
from scipy.spatial.distance import pdist

from monotracker.sim.phantom import default_phantom


def _ellipsoid_value(ph, p):
    return float(np.sum(((p - ph.centre_lps) / ph.skin_semi_axes_mm) ** 2))


def test_fiducials_rest_on_the_skin():
    ph = default_phantom()
    for c in ph.fiducial_centres_lps:
        # The contact point is the centre minus R along the normal; it must be on the skin.
        u = c - ph.centre_lps
        p, n = ph.skin_point(u)
        contact = c - ph.fiducial_radius_mm * n
        assert abs(_ellipsoid_value(ph, contact) - 1.0) < 1e-2
        # and the ball is outside the head
        assert _ellipsoid_value(ph, c) > 1.0


def test_fiducials_are_distinct_and_face_the_camera_side():
    ph = default_phantom()
    c = ph.fiducial_centres_lps
    assert c.shape == (9, 3)
    assert pdist(c).min() > 4 * ph.fiducial_radius_mm
    normals = np.array([ph.skin_point(x - ph.centre_lps)[1] for x in c])
    assert np.all(normals @ ph.view_direction_lps > np.cos(np.radians(60)))


def test_sample_plan_goes_from_skin_to_inside_the_brain():
    ph = default_phantom()
    assert abs(_ellipsoid_value(ph, ph.sample_entry_lps) - 1.0) < 1e-9
    inner = ph.skin_semi_axes_mm - ph.scalp_thickness_mm - ph.skull_thickness_mm
    assert np.sum(((ph.sample_target_lps - ph.centre_lps) / inner) ** 2) < 0.5
