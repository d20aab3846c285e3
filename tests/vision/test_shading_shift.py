"""The opt-in shading shift (vision/shading_shift.py, issue 28) on balls drawn here from their
geometry: a flat ball keeps its edge centre; a ball lit from one side is moved towards its lit
side by the measured amounts; no move exceeds its cap; the detector leaves it off by default."""

import numpy as np
import pytest

from monotracker.vision import shading_shift
from monotracker.vision.detection import BlobRules
from monotracker.vision.shading_shift import lit_side, shaded_centre


def _ball(size, centre, radius, light_dir=None, base=120.0, gain=100.0):
    """Grey image of a disc on a flat background; inside, brightness base + gain x the
    Lambertian cosine of a sphere lit from ``light_dir`` (unit 2-vector in the image plane,
    tilted 45 deg towards the camera; None: a flat disc)."""
    yy, xx = np.mgrid[0:size, 0:size].astype(float)
    dx, dy = (xx - centre[0]) / radius, (yy - centre[1]) / radius
    r2 = dx * dx + dy * dy
    img = np.full((size, size), 40.0)
    inside = r2 < 1.0
    if light_dir is None:
        img[inside] = base
    else:
        nz = np.sqrt(np.clip(1.0 - r2, 0.0, None))
        lx, ly = np.asarray(light_dir, float) / np.sqrt(2.0)
        lz = 1.0 / np.sqrt(2.0)
        cos = np.clip(dx * lx + dy * ly + nz * lz, 0.0, None)
        img[inside] = (base + gain * cos)[inside]
    return img


def test_a_flat_ball_keeps_its_edge_centre():
    img = _ball(80, (40.0, 40.0), 12.0)
    u = lit_side(img, (40.0, 40.0), 12.0)
    assert np.hypot(*u) < shading_shift.MIN_LIT
    centre, moved = shaded_centre(img, (40.0, 40.0), (41.0, 39.5), 12.0)
    assert moved == 0.0 and np.allclose(centre, (40.0, 40.0))


@pytest.mark.parametrize("light", [(1.0, 0.0), (0.0, -1.0), (-0.6, 0.8)])
def test_a_ball_lit_from_one_side_moves_towards_it(light):
    c = (40.0, 41.0)
    img = _ball(80, c, 12.0, light_dir=light)
    u = lit_side(img, c, 12.0)
    assert np.hypot(*u) >= shading_shift.MIN_LIT
    assert float(np.dot(u, light)) / np.hypot(*u) > 0.99          # the brightness centroid lies on the lit side
    # blob contour where the edge fit is: only the lit-side term moves the centre
    centre, moved = shaded_centre(img, c, c, 12.0)
    step = np.asarray(centre) - c
    assert moved == pytest.approx(shading_shift.LIT_SHIFT_PX, abs=1e-9)
    assert np.allclose(step, shading_shift.LIT_SHIFT_PX * np.asarray(light), atol=1e-3)
    # a blob contour 0.5 px across the lit direction adds BLOB_WEIGHT of that offset
    across = np.array([-light[1], light[0]])
    centre2, _ = shaded_centre(img, c, np.asarray(c) + 0.5 * across, 12.0)
    assert np.allclose(np.asarray(centre2) - centre, shading_shift.BLOB_WEIGHT * 0.5 * across, atol=1e-9)


def test_no_move_beyond_the_cap():
    c = (40.0, 40.0)
    img = _ball(80, c, 10.0, light_dir=(1.0, 0.0))
    centre, moved = shaded_centre(img, c, (30.0, 40.0), 10.0)        # a contour 10 px off (a cut blob)
    assert moved == pytest.approx(shading_shift.MAX_SHIFT * 10.0)
    assert np.hypot(*(np.asarray(centre) - c)) == pytest.approx(shading_shift.MAX_SHIFT * 10.0)


def test_a_ball_at_the_frame_edge_is_left_alone():
    img = _ball(40, (5.0, 20.0), 12.0, light_dir=(1.0, 0.0))
    assert np.allclose(lit_side(img, (5.0, 20.0), 12.0), 0.0)


def test_off_by_default():
    # on our simulator and the independent renders it moves right centres (docs/vision.md)
    assert BlobRules().shading_shift is False
