"""Navigation views (ui/navigation.py) against an independent truth: a synthetic CT written with
SimpleITK with an oblique, axis-flipped direction matrix, dense balls put at known LPS points
through SimpleITK's own physical->index mapping (not ours). Each ball must appear where the
orientation letters say, in every view; the probe's-eye view must be centred on the path."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from monotracker.ct.volume import Volume
from monotracker.ui import navigation as nav

CENTRE = np.array([10.0, -20.0, 30.0])  # LPS mm, the volume's middle
SIDE = 1.0  # mm voxels


def _volume(balls_lps, radius=4.0, n=160):
    """Air-filled (-1000 HU) cube, n voxels a side, with 3000 HU balls at ``balls_lps``; its
    direction is a rotation with the i axis flipped (as some scanners write it)."""
    R = Rotation.from_euler("zyx", [20, -10, 15], degrees=True).as_matrix() @ np.diag([-1.0, 1.0, 1.0])
    img = sitk.Image(n, n, n, sitk.sitkInt16)
    img.SetSpacing((SIDE, SIDE, SIDE))
    img.SetDirection(tuple(R.ravel()))
    img.SetOrigin((0.0, 0.0, 0.0))
    mid = img.TransformContinuousIndexToPhysicalPoint(((n - 1) / 2,) * 3)
    img.SetOrigin(tuple(CENTRE - np.array(mid)))
    arr = np.full((n, n, n), -1000, np.int16)
    kk, jj, ii = np.mgrid[0:n, 0:n, 0:n]
    for b in balls_lps:
        ci = np.array(img.TransformPhysicalPointToContinuousIndex(tuple(float(v) for v in b)))
        inside = (ii - ci[0]) ** 2 + (jj - ci[1]) ** 2 + (kk - ci[2]) ** 2 <= (radius / SIDE) ** 2
        arr[inside] = 3000
    out = sitk.GetImageFromArray(arr)
    out.CopyInformation(img)
    return Volume.from_image(out, "synthetic")


def _blobs(hu, thr=1000.0):
    """Centroids (col, row) of the bright blobs of an image (scipy labelling)."""
    from scipy import ndimage

    lab, n = ndimage.label(hu > thr)
    return [np.array(ndimage.center_of_mass(hu > thr, lab, i + 1))[::-1] for i in range(n)]


def _side(view, px):
    """Which edges the pixel lies towards: (horizontal side, vertical side)."""
    dc, dr = px[0] - view.c0, px[1] - view.c0
    return ("right" if dc > 0 else "left"), ("bottom" if dr > 0 else "top")


def test_letters_follow_the_radiological_convention():
    views = nav.plane_views(CENTRE)
    assert views["axial"].letters() == {"right": "L", "left": "R", "top": "A", "bottom": "P"}
    assert views["coronal"].letters() == {"right": "L", "left": "R", "top": "S", "bottom": "I"}
    assert views["sagittal"].letters() == {"right": "P", "left": "A", "top": "S", "bottom": "I"}
    assert nav.direction_letters([0.0, -0.7, 0.72]) == "SA"
    assert nav.direction_letters([0.0, 0.2, -1.0]) == "I"


def test_a_marker_left_anterior_superior_shows_on_the_lettered_sides():
    m = CENTRE + np.array([30.0, -25.0, 20.0])  # patient Left, Anterior, Superior of the centre
    vol = _volume([m])
    # each plane through the marker, centred off it so the marker lands away from the centre
    points = {"axial": (CENTRE[0], CENTRE[1], m[2]), "coronal": (CENTRE[0], m[1], CENTRE[2]),
              "sagittal": (m[0], CENTRE[1], CENTRE[2])}
    expected = {"axial": ("L", "A"), "coronal": ("L", "S"), "sagittal": ("A", "S")}
    for name, p in points.items():
        view = nav.plane_views(np.array(p))[name]
        hu = nav.sample_plane(vol, view)
        blobs = _blobs(hu)
        assert len(blobs) == 1, name
        got = blobs[0]
        assert np.allclose(got, view.to_pixel(m)[0], atol=1.0), name  # where the geometry says
        h, v = _side(view, got)
        letters = view.letters()
        assert letters[h][0] == expected[name][0], (name, letters, h)
        assert letters[v][0] == expected[name][1], (name, letters, v)
        img = nav.render_view(hu, view, width=2000, level=400)
        assert img.shape == (2 * view.size, 2 * view.size, 3) and img.dtype == np.uint8


def test_probe_views_are_centred_on_the_path_and_lettered():
    e = CENTRE + np.array([-20.0, -30.0, 45.0])
    t = CENTRE + np.array([15.0, 10.0, -10.0])
    d = (t - e) / np.linalg.norm(t - e)
    on_path = e + 0.6 * np.linalg.norm(t - e) * d  # a ball on the path, 60 % of the way in
    u_left = np.array([1.0, 0.0, 0.0]) - d[0] * d
    u_left /= np.linalg.norm(u_left)
    side_ball = on_path + 25.0 * u_left  # beside it, towards the patient's left
    vol = _volume([on_path, side_ball], radius=3.0)
    tip = on_path + 7.0 * np.cross(d, u_left)  # a tip off the path but at that ball's depth
    views = nav.plane_views(tip, e, t)
    probe, along = views["probe"], views["along"]
    assert np.allclose(probe.normal, d) and abs(float(probe.depth(on_path)[0])) < 1e-9

    blobs = _blobs(nav.sample_plane(vol, probe))
    assert len(blobs) == 2
    centre_blob = min(blobs, key=lambda b: np.hypot(*(b - probe.c0)))
    assert np.hypot(*(centre_blob - probe.c0)) < 1.0  # the path is the centre of the probe's eye
    other = max(blobs, key=lambda b: np.hypot(*(b - probe.c0)))
    h, v = _side(probe, other)
    dc, dr = other - probe.c0
    main = h if abs(dc) > abs(dr) else v
    assert "L" in probe.letters()[main]

    hu = nav.sample_plane(vol, along)
    blobs = _blobs(hu)
    on = min(blobs, key=lambda b: abs(b[0] - along.c0))
    assert abs(on[0] - along.c0) < 1.0  # the path runs down the centre column
    assert np.allclose(on, along.to_pixel(on_path)[0], atol=1.0)
    ent, tgt = along.to_pixel([e, t])
    assert ent[1] < tgt[1] and abs(ent[0] - along.c0) < 1e-6  # entry above the target
    assert along.letters()["right"][0] == "L"


def test_tip_maps_into_ct_through_hand_eye_and_registration():
    T_base_ct = np.eye(4)
    T_base_ct[:3, :3] = Rotation.from_euler("xyz", [30, -40, 120], degrees=True).as_matrix()
    T_base_ct[:3, 3] = [600.0, -100.0, 250.0]
    tip_ct = np.array([12.0, -34.0, 56.0])
    axis_ct = np.array([0.0, 0.6, -0.8])
    T_ct_tip = np.eye(4)
    T_ct_tip[:3, :3] = Rotation.align_vectors([axis_ct], [[0.0, 0.0, 1.0]])[0].as_matrix()
    T_ct_tip[:3, 3] = tip_ct
    fresh = SimpleNamespace(trusted=True, stale=False, age_s=0.03, reason="pose trusted")
    snap = SimpleNamespace(scene=SimpleNamespace(T_base_ct=T_base_ct, T_base_tip=T_base_ct @ T_ct_tip),
                           plan=SimpleNamespace(target_lps_mm=np.zeros(3)), pose=fresh)
    p, a = nav.tip_in_ct(snap)
    assert np.allclose(p, tip_ct, atol=1e-9) and np.allclose(a, axis_ct, atol=1e-9)
    np_ = nav.nav_point(snap, np.zeros(3))
    assert np_.source == "tip" and np.allclose(np_.point, tip_ct)
    snap = SimpleNamespace(scene=SimpleNamespace(T_base_ct=None, T_base_tip=None),
                           plan=SimpleNamespace(target_lps_mm=np.array([1.0, 2.0, 3.0])), pose=None)
    np_ = nav.nav_point(snap, np.zeros(3))
    assert np_.source == "target" and np.allclose(np_.point, [1, 2, 3])


@pytest.mark.parametrize("preset", sorted(nav.WL_PRESETS))
def test_window_level_presets_change_the_pixels(preset):
    view = nav.plane_views(CENTRE)["axial"]
    hu = np.tile(np.linspace(-1000, 2000, view.size, dtype=np.float32), (view.size, 1))  # HU ramp left to right
    w, lv = nav.WL_PRESETS[preset]
    img = nav.render_view(hu, view, width=w, level=lv, scale=1)
    other = nav.render_view(hu, view, width=3000, level=500, scale=1)
    row = view.size // 4  # clear of the letters and labels
    grey = img[row, :, 0].astype(int)
    # the window's middle (level) is mid-grey in the image where hu == level, black below, white above
    col = int(np.argmin(np.abs(hu[row] - lv)))
    assert grey[0] == 0 and grey[-1] == 255
    assert abs(grey[col] - 127) < 30
    assert np.abs(img.astype(int) - other.astype(int)).mean() > 5


def test_a_click_ray_on_a_tile_gives_the_point_drawn_there_and_off_tile_gives_none():
    from monotracker.ui.navigation_panel import TILE, NavigationScene, grid

    sc = NavigationScene(SimpleNamespace(client_id="t"))
    try:
        v = nav.plane_views(CENTRE, CENTRE + np.array([0.0, -30.0, 40.0]), CENTRE)["probe"]
        sc._tiles = {"probe": (None, v, (0.1, -0.2))}
        p = v.to_lps(40.3, 170.7)
        w = sc.world_of("probe", p)
        cam = np.array([0.05, 0.02, -0.6])  # an oblique ray, as from a camera off the tile's axis
        got = sc.pick("probe", cam, (w - cam) / np.linalg.norm(w - cam))
        assert np.allclose(got, p, atol=1e-9)
        assert sc.pick("probe", cam, (w + np.array([TILE, 0.0, 0.0])) - cam) is None
        assert sc.pick("axial", cam, w - cam) is None  # no such tile shown
    finally:
        sc.close()
    assert grid(5, 1.6) == (3, 2) and grid(5, 0.6) == (2, 3) and grid(3, 1.6) == (2, 2)
