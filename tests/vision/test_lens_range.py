"""The lens range check (vision/lens_range.py): a ball's image radius against the sphere's
projected silhouette, and which calibrations it flags."""

import numpy as np
import pytest

from monotracker.planning.problem import CameraSpace
from monotracker.vision import lens_range
from monotracker.vision.camera_model import CameraModel, default_camera


def _silhouette_radius_px(camera, radius_mm, distance_mm):
    """Mean distance (px) from the projected centre of the sphere's outline: the points where lines
    of sight from the pinhole touch a sphere of ``radius_mm`` centred ``distance_mm`` down the axis."""
    a = np.arcsin(radius_mm / distance_mm)
    L = np.sqrt(distance_mm**2 - radius_mm**2)            # pinhole -> tangent point
    phi = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
    pts = L * np.stack([np.sin(a) * np.cos(phi), np.sin(a) * np.sin(phi), np.full_like(phi, np.cos(a))], axis=1)
    px = camera.project(pts)
    return float(np.mean(np.linalg.norm(px - px.mean(axis=0), axis=1)))


@pytest.mark.parametrize("f, z", [(1100.0, 400.0), (800.0, 400.0), (1650.0, 250.0)])
def test_the_radius_is_the_projected_silhouette(f, z):
    pinhole = CameraModel(np.array([[f, 0, 640.0], [0, f, 360.0], [0, 0, 1]]), np.zeros(5), (1280, 720))
    assert lens_range.ball_radius_px(pinhole, 4.0, z) == pytest.approx(_silhouette_radius_px(pinhole, 4.0, z), rel=1e-9)


def test_the_default_cameras_mild_distortion_changes_it_under_a_percent():
    cam = default_camera()
    assert lens_range.ball_radius_px(cam, 4.0, 400.0) == pytest.approx(_silhouette_radius_px(cam, 4.0, 400.0), rel=0.01)


def test_the_judged_distance_is_the_planners_closest():
    assert lens_range.JUDGED_DISTANCE_MM == CameraSpace(axis=np.array([0.0, 0.0, 1.0])).distance_mm[0] == 400.0


def _wide():
    """The rendered sets' short lens: f = 800 px on the generator's 1280 x 720 sensor."""
    cam = default_camera()
    K = cam.K.copy()
    K[0, 0] = K[1, 1] = 800.0
    return CameraModel(K, cam.dist, cam.image_size)


def test_the_judged_lenses_pass_and_the_short_one_is_named():
    assert lens_range.short_lens_message(default_camera(), 4.0) == ""              # 11 px from 400 mm
    assert lens_range.short_lens_message(default_camera().scaled(1.5), 4.0) == ""  # 1920 x 1080: 16.5 px
    why = lens_range.short_lens_message(_wide(), 4.0)
    assert "8.0 px" in why and "400 mm" in why and "longer lens" in why
    # the same sensor binned 2 x 2 halves the focal length in px: 5.5 px
    assert "5.5 px" in lens_range.short_lens_message(default_camera().adapted("bin:2"), 4.0)
    # smaller balls make the same lens short; a given distance is used as given
    assert lens_range.short_lens_message(default_camera(), 3.0) != ""
    assert lens_range.short_lens_message(_wide(), 4.0, distance_mm=300.0) == ""


def test_nonsense_is_refused():
    with pytest.raises(ValueError):
        lens_range.ball_radius_px(default_camera(), 4.0, 3.0)


@pytest.mark.parametrize("radius", [0.0, -1.0, float("nan"), 500.0])
def test_a_radius_that_is_no_balls_is_not_judged_short(radius):
    """The tracker asks :func:`is_short` at construction: a radius that is no ball's leaves the
    tracker as it was (its own checks), never an exception from the lens rule."""
    assert not lens_range.is_short(_wide(), radius)
    assert lens_range.is_short(_wide(), 4.0) and not lens_range.is_short(default_camera(), 4.0)
    assert lens_range.short_lens_message(_wide(), radius) == ""
