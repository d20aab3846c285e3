"""The simulated camera casts skin rays only where the head can be (``sim/ray_geometry._skin``):
what it skips must be rays the full cast gives no coverage, and what it casts must be the full
cast's answer, bit for bit (the renders, and every test built on them, stay what they were)."""

import numpy as np
import pytest

from monotracker.sim.camera_sim import SimulatedCamera
from monotracker.sim.or_layout import default_layout


@pytest.mark.parametrize("optics", [None, "photo"])
@pytest.mark.parametrize("distance_scale", [1.0, 0.35])
def test_the_culled_skin_cast_equals_the_full_cast(optics, distance_scale):
    layout = default_layout()
    T = np.array(layout.T_cam_ct0, float)
    cam = SimulatedCamera(trajectory=layout.motion("breathing", seed=1), T_cam_world=T, optics=optics, seed=0)
    px_per_rad = cam.K[0, 0] * cam._low_scale
    culled_some = False
    for t in np.linspace(0.0, 4.0, 7):
        Tt = cam.T_cam_ct_at(float(t))
        R, tr = Tt[:3, :3], Tt[:3, 3] * distance_scale          # 0.35: the head close, filling the frame
        cov, shade, spec = cam._skin(cam._rays_low, R, tr, px_per_rad)
        c_cam = R @ cam.phantom.centre_lps + tr
        scale = float(np.mean(cam.phantom.skin_semi_axes_mm)) / float(np.linalg.norm(c_cam)) * px_per_rad
        cov_f, shade_f, spec_f = cam._skin_rays(cam._rays_low, R, c_cam, scale)   # every ray cast
        assert np.array_equal(cov, cov_f)
        m = cov_f > 0
        assert m.any() and np.array_equal(shade[m], shade_f[m])
        assert (spec is None) == (spec_f is None) == (optics is None)
        if spec is not None:
            assert np.array_equal(spec[m], spec_f[m])
        culled_some |= bool(np.any(shade == 0))
    assert culled_some or distance_scale < 1.0       # the sample view skips most of the frame
