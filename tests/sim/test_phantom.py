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


def test_placing_a_layout_on_the_skin_moves_a_resting_ball_nowhere():
    """``with_fiducials_at``: a ball whose centre already rests on the skin (one radius out along
    the skin's normal) stays where it is, so a placed layout placed again is unchanged; and every
    placed ball rests on the skin (independent check: the skin point found from the ball's own
    centre by the analytic ellipsoid's normal). Before, each placement moved the phantom's own
    balls by 0.2-0.97 mm (the layout benchmark rendered balls 1 mm from where its tracker was told
    they were)."""
    ph = default_phantom()
    X0 = ph.fiducial_centres_lps
    np.testing.assert_allclose(ph.with_fiducials_at(X0).fiducial_centres_lps, X0, atol=1e-5)
    Y = X0 + np.random.default_rng(0).normal(scale=3.0, size=X0.shape)      # off the skin
    Y1 = ph.with_fiducials_at(Y).fiducial_centres_lps
    np.testing.assert_allclose(default_phantom().with_fiducials_at(Y1).fiducial_centres_lps, Y1, atol=1e-5)
    from scipy.optimize import minimize

    a = ph.skin_semi_axes_mm
    for c in Y1:
        # resting on the skin: the nearest point of the skin ellipsoid is one radius away
        # (found by a general minimiser over the ellipsoid's angles, not by the phantom's own code)
        d = (c - ph.centre_lps) / a
        start = [np.arccos(d[2] / np.linalg.norm(d)), np.arctan2(d[1], d[0])]

        def dist(t, c=c):
            e = ph.centre_lps + a * np.array([np.sin(t[0]) * np.cos(t[1]), np.sin(t[0]) * np.sin(t[1]), np.cos(t[0])])
            return float(np.linalg.norm(c - e))

        best = minimize(dist, start, method="Nelder-Mead", options=dict(xatol=1e-9, fatol=1e-9, maxiter=4000))
        assert abs(best.fun - ph.fiducial_radius_mm) < 1e-3, (best.fun, ph.fiducial_radius_mm)
