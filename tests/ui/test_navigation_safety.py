"""Navigation view safety (review findings): the slices follow the needle tip only through a
current trusted pose and say why not otherwise; a new CT never reuses the old one's slices; a
click is mapped only when every image the browser may be showing puts the same point under it."""

from __future__ import annotations

import contextlib
from types import SimpleNamespace

import numpy as np
import pytest
import SimpleITK as sitk

from monotracker.ct.volume import Volume
from monotracker.ui import navigation as nav
from monotracker.ui import navigation_panel as navp

TARGET = np.array([2.0, -3.0, 4.0])
ENTRY = TARGET + np.array([0.0, -40.0, 30.0])
TIP = np.array([5.0, 6.0, -7.0])
MAX_AGE = 0.15


def _pose(trusted=True, stale=False, age_s=0.03, reason="pose trusted"):
    return SimpleNamespace(trusted=trusted, stale=stale, age_s=age_s, reason=reason)


def _snap(pose, tip=True):
    T_base_ct = np.eye(4)
    T_base_ct[:3, 3] = [500.0, 0.0, 200.0]
    T_ct_tip = np.eye(4)
    T_ct_tip[:3, 3] = TIP
    return SimpleNamespace(
        scene=SimpleNamespace(T_base_ct=T_base_ct, T_base_tip=(T_base_ct @ T_ct_tip) if tip else None),
        plan=SimpleNamespace(target_lps_mm=TARGET, entry_lps_mm=ENTRY), pose=pose, fiducials=())


@pytest.mark.parametrize("pose, why", [
    (None, "no pose estimate"),
    (_pose(trusted=False, reason="3 fiducials visible"), "pose not trusted (3 fiducials visible)"),
    (_pose(trusted=False, stale=True, reason="camera frozen"), "pose stale (camera frozen)"),
    (_pose(age_s=0.4), "pose stale (400 ms old, limit 150 ms)"),
])
def test_a_stale_or_untrusted_pose_does_not_drive_the_slices_and_the_line_says_why(pose, why):
    np_ = nav.nav_point(_snap(pose), np.zeros(3), live=True, max_pose_age_s=MAX_AGE)
    assert np_.source == "target" and np.allclose(np_.point, TARGET)
    assert np_.tip is None and np_.tip_axis is None
    assert np_.note.startswith(f"tip unknown: {why}")
    line = navp.describe(np_, ENTRY, TARGET)
    assert "tip unknown" in line and why in line
    assert "(live)" not in line and "mm to target" not in line


def test_a_fresh_trusted_pose_drives_the_slices():
    np_ = nav.nav_point(_snap(_pose(age_s=0.1)), np.zeros(3), live=True, max_pose_age_s=MAX_AGE)
    assert np_.source == "tip" and np.allclose(np_.point, TIP) and np_.note == ""
    line = navp.describe(np_, ENTRY, TARGET)
    assert "needle tip (live)" in line and "mm to target" in line and "tip unknown" not in line
    # the limit is the caller's (the session's max_pose_age_s)
    assert nav.nav_point(_snap(_pose(age_s=0.1)), np.zeros(3), max_pose_age_s=0.05).source == "target"
    # no robot tip: the target, and the line says so; the plan step (not live) says nothing
    np_ = nav.nav_point(_snap(_pose(), tip=False), np.zeros(3), live=True)
    assert np_.source == "target" and "no needle pose" in np_.note
    assert nav.nav_point(_snap(None), np.zeros(3), live=False).note == ""


def _volume(ball_lps=None, n=48):
    arr = np.full((n, n, n), -1000, np.int16)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing((2.0, 2.0, 2.0))
    img.SetOrigin(tuple(TARGET - (n - 1)))  # the target in the middle
    if ball_lps is not None:
        kk, jj, ii = np.mgrid[0:n, 0:n, 0:n]
        ci = np.array(img.TransformPhysicalPointToContinuousIndex(tuple(float(v) for v in ball_lps)))
        arr[(ii - ci[0]) ** 2 + (jj - ci[1]) ** 2 + (kk - ci[2]) ** 2 <= 9] = 3000
        out = sitk.GetImageFromArray(arr)
        out.CopyInformation(img)
        img = out
    return Volume.from_image(img, "synthetic")


class _Handle:
    def __init__(self, image):
        self.image = image

    def on_click(self, f):
        self.click = f
        return f


class _Scene:
    def reset(self):
        pass

    def add_image(self, _name, image, *_a, **_k):
        return _Handle(image)


def _fake_view(vol):
    cam = SimpleNamespace(aspect=1.6, image_height=800, fov=0.9, update_timestamp=1.0)
    said = []
    view = SimpleNamespace(
        client_id="t", scene=_Scene(), say=lambda ok, msg: said.append((ok, msg)),
        client=SimpleNamespace(camera=cam, atomic=contextlib.nullcontext),
        safe=lambda _what: (lambda f: f), said=said,
        session=SimpleNamespace(volume=lambda: view.vol, config=SimpleNamespace(max_pose_age_s=MAX_AGE)))
    view.vol = vol
    return view


def _scene(vol):
    view = _fake_view(vol)
    sc = navp.NavigationScene(view)
    sc.close()  # no worker: the test renders
    sc._thread.join(5)
    panel = SimpleNamespace(key="robot", live=True, state=lambda: (True, 2000.0, 400.0, None),
                            h_info=SimpleNamespace(content=""))
    return view, sc, panel


def test_the_panel_follows_the_tip_only_while_the_pose_is_current():
    view, sc, panel = _scene(_volume())
    sc._request = (_snap(_pose()), panel)
    sc._render_once()
    assert np.allclose(sc.tiles()["axial"][0].centre_lps, TIP)
    assert "data-source='tip'" in panel.h_info.content and "needle tip (live)" in panel.h_info.content
    sc._request = (_snap(_pose(age_s=0.5)), panel)  # the session's limit (0.15 s) from its config
    sc._render_once()
    assert np.allclose(sc.tiles()["axial"][0].centre_lps, TARGET)
    assert "data-source='target'" in panel.h_info.content
    assert "tip unknown: pose stale (500 ms old" in panel.h_info.content
    seq = sc._seq
    sc._request = (_snap(_pose(trusted=False, reason="2 fiducials visible")), panel)
    sc._render_once()  # the same images; only the line changes
    assert sc._seq == seq and "pose not trusted (2 fiducials visible)" in panel.h_info.content


def test_a_new_ct_is_sliced_afresh_not_served_from_the_old_ones_cache():
    view, sc, panel = _scene(_volume())
    sc._request = (_snap(None), panel)
    sc._render_once()
    v = sc.tiles()["axial"][0]
    assert sc._hu(view.vol, v).max() < 0  # air only
    seq = sc._seq
    view.vol = _volume(ball_lps=TARGET)  # another CT (a new object; the old one is dropped)
    sc._render_once()
    assert sc._seq == seq + 1  # re-rendered
    assert sc._vol is view.vol and sc._hu(view.vol, v).max() > 1000  # the new CT's ball
    gen = sc._volume_gen(view.vol)
    assert sc._volume_gen(view.vol) == gen and sc._volume_gen(_volume()) == gen + 1


def test_a_click_maps_only_where_every_image_the_browser_may_show_agrees():
    view, sc, _panel = _scene(_volume())
    v1 = nav.plane_views(TARGET)["axial"]
    v2 = nav.plane_views(TARGET + np.array([5.0, 0.0, 0.0]))["axial"]  # the slices moved 5 mm
    jitter = nav.plane_views(TARGET + np.array([5.1, 0.0, 0.0]))["axial"]  # 0.1 mm from v2
    xy = (0.1, -0.2)
    cam = np.array([0.05, 0.02, -0.6])

    def ray(v, p):
        sc._tiles = {"axial": (None, v, xy)}
        w = sc.world_of("axial", p)
        return cam, (w - cam) / np.linalg.norm(w - cam)

    p = TARGET + np.array([10.0, -7.0, 0.0])
    with sc._lock:
        sc._remember("axial", v1, xy, now=0.0)
        sc._remember("axial", v2, xy, now=10.0)
    o, d = ray(v2, p)  # the click is on the pixel where the newest image shows p
    got, why = sc.pick_checked("axial", o, d, now=10.3)  # the browser may still show v1's image
    assert got is None and "moved under the click" in why and "5.0 mm" in why
    got, why = sc.pick_checked("axial", o, d, now=11.5)  # v2 has been on screen long enough
    assert np.allclose(got, p, atol=1e-9) and why == ""
    # a geometry that changed less than the tolerance (tracking jitter) does not block clicks
    with sc._lock:
        sc._remember("axial", jitter, xy, now=20.0)
    got, why = sc.pick_checked("axial", *ray(jitter, p), now=20.1)
    assert got is not None and why == "" and np.linalg.norm(got - p) < 1e-9
    # a layout change (the tile moved in the canvas) refuses a click that may be on the old one
    with sc._lock:
        sc._remember("axial", jitter, (0.3, -0.2), now=30.0)
    sc._tiles = {"axial": (None, jitter, (0.3, -0.2))}
    w = sc.world_of("axial", p)
    assert sc.pick("axial", cam, w - cam, now=30.2) is None
    assert sc.pick("axial", cam, w - cam, now=32.0) is not None
    # the history stays short: the window and the one image before it
    with sc._lock:
        for i in range(50):
            sc._remember("axial", jitter, xy, now=100.0 + 0.25 * i)
    assert len(sc._history["axial"]) <= 6
