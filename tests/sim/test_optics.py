"""The photo-like imaging chain against physics worked out by hand (Poisson statistics, PSF
moments, colour preservation) and the photo-like render's truth."""

import cv2
import numpy as np
import pytest

from monotracker.sim.camera_sim import SimulatedCamera
from monotracker.sim.optics import DRAPE_BGR, Optics, OpticsChain, disc_psf


def test_disc_psf_is_a_normalised_uniform_disc():
    k = disc_psf(3.0)
    assert k.shape == (9, 9) and abs(k.sum() - 1) < 1e-6
    assert np.allclose(k, k[::-1]) and np.allclose(k, k.T)
    # second moment of a uniform disc of radius R: E[x^2] = R^2 / 4 (+ 1/12 for the pixel box)
    g = np.arange(9) - 4
    ex2 = (k.sum(0) * g**2).sum()
    assert abs(ex2 - (9 / 4 + 1 / 12)) < 0.05
    assert disc_psf(0.1).shape == (1, 1)


def test_sensor_noise_follows_shot_and_read_noise():
    """Flat grey, linear response (gamma 1), no Bayer/JPEG/blur: the output's std in grey
    levels is sqrt(e + read^2) / full_well * 255 with e the electrons of that grey level."""
    o = Optics(defocus_px=0, gamma=1.0, vignetting=0.0, bayer=False, full_well_e=2000, read_noise_e=5,
               jpeg_quality=0)
    ch = OpticsChain(o, (200, 100), seed=3)
    for level in (40.0, 160.0):
        out = ch.apply(np.full((100, 200, 3), level, np.float32), key=0.5).astype(float)
        e = level / 255 * 2000
        expect = np.sqrt(e + 25) / 2000 * 255
        assert abs(out.mean() - level) < 0.5
        assert abs(out.std() - expect) / expect < 0.1, (out.std(), expect)


def test_chain_is_deterministic_per_frame_key():
    ch = OpticsChain(Optics(), (160, 120), seed=1)
    img = np.full((120, 160, 3), 100, np.float32)
    a, b, c = ch.apply(img, 0.1), ch.apply(img, 0.1), ch.apply(img, 0.2)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_bayer_demosaic_keeps_flat_colours():
    o = Optics(defocus_px=0, vignetting=0.0, full_well_e=1e7, read_noise_e=0, jpeg_quality=0)
    ch = OpticsChain(o, (64, 48), seed=0)
    for col in ((45, 160, 40), DRAPE_BGR["teal"], (175, 195, 215)):
        out = ch.apply(np.full((48, 64, 3), col, np.float32), 0.0)
        assert np.abs(out[8:-8, 8:-8].reshape(-1, 3).mean(0) - col).max() < 1.5


def test_photo_render_keeps_truth_and_differs_from_simple_render():
    simple = SimulatedCamera(seed=2)
    photo = SimulatedCamera(seed=2, optics="photo")
    a, ta = simple.render(0.4)
    b, tb = photo.render(0.4)
    assert np.allclose(ta.ellipse_centres_px, tb.ellipse_centres_px)
    assert np.array_equal(ta.visible, tb.visible)
    assert b.shape == a.shape and b.dtype == np.uint8 and np.abs(a.astype(int) - b).mean() > 5
    b2, _ = SimulatedCamera(seed=2, optics="photo").render(0.4)
    assert np.array_equal(b, b2)
    # a specular highlight on each ball: its brightest pixel is near-white, its mean is green
    for c, r in zip(tb.ellipse_centres_px, tb.radius_px):
        x, y = np.round(c).astype(int)
        patch = b[y - int(r) + 1:y + int(r), x - int(r) + 1:x + int(r)].reshape(-1, 3).astype(int)
        assert patch.sum(1).max() > 450 and patch.mean(0)[1] > patch.mean(0)[2]


@pytest.mark.parametrize("drapes", ["teal", "blue", "green-blue"])
def test_drape_colours_in_the_background(drapes):
    """The background's hue is the drape's nominal hue (shading, gamma, noise do not move it)."""
    hue = int(cv2.cvtColor(np.uint8([[DRAPE_BGR[drapes]]]), cv2.COLOR_BGR2HSV)[0, 0, 0])
    cam = SimulatedCamera(seed=0, optics=Optics(drapes=drapes, jpeg_quality=0))
    img, _ = cam.render(0.0)
    corner = cv2.cvtColor(img[5:60, 5:60], cv2.COLOR_BGR2HSV).reshape(-1, 3)
    assert abs(np.median(corner[:, 0]) - hue) <= 4


def test_unknown_preset_is_a_clear_error():
    with pytest.raises(ValueError, match="optics preset"):
        SimulatedCamera(optics="fancy")


@pytest.mark.parametrize("defocus", [0.0, 1.5])
def test_ball_edges_mix_in_linear_light(defocus):
    """A pixel integrates photons: where a ball covers a share ``a`` of it, its linear radiance
    is ``a * ball + (1 - a) * background``, whatever the blur after it. So in a channel where
    the ball is black (dye (0, 160, 0)), ``1 - R_lin / R_lin(background)`` summed over the ball
    is its silhouette's area, checked against the area of the analytic silhouette cone
    (``_full_coverage``). Mixing gamma-encoded values instead makes the dark ball ~4 % larger."""
    o = Optics(drapes="blue", defocus_px=defocus, vignetting=0.0, bayer=False, full_well_e=1e9,
               read_noise_e=0.0, jpeg_quality=0, hair_density=0.0, ball_specular=0.0, skin_specular=0.0)
    cam = SimulatedCamera(optics=o, exposure_s=0.0, ball_bgr=(0.0, 160.0, 0.0))
    img, tr = cam.render(0.0)
    red = (img[..., 2].astype(float) / 255.0) ** o.gamma
    C = (cam.T_cam_ct_at(0.0) @ np.c_[cam.fiducials_ct, np.ones(len(cam.fiducials_ct))].T).T[:, :3]
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    checked = 0
    for j in np.where(tr.visible)[0]:
        c, r = tr.ellipse_centres_px[j], tr.radius_px[j]
        d = np.hypot(xx - c[0], yy - c[1])
        ring = (d > r + 4) & (d < r + 7)
        A = np.c_[xx[ring], yy[ring], np.ones(ring.sum())]
        plane = np.linalg.lstsq(A, red[ring], rcond=None)[0]      # skin shading varies slowly
        disc = d < r + 3.5
        bg = np.c_[xx[disc], yy[disc], np.ones(disc.sum())] @ plane
        area = float(np.sum(1.0 - red[disc] / bg))
        roi = cam._sphere_roi(tr.projected_centres_px[j], r, img.shape[1], img.shape[0])
        truth = cam._full_coverage(C[j], cam.phantom.fiducial_radius_mm, roi)
        assert abs(area - truth) < 0.01 * truth, (j, area, truth)
        checked += 1
    assert checked >= 6
