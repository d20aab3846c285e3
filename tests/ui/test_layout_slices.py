"""The layout planner's suggested balls on the Plan step's slices (issue 31): numbered S1..Sn as in
the 3D view, on the step's slice images and on its navigation views, only on the planes they lie
near, and not at the other steps. View level: the gui and scene are doubles; the truth is a
synthetic CT with a dense ball put at each suggested position through SimpleITK's own
physical->index mapping (not ours), so each blue ring must circle the ball the CT shows there."""

from __future__ import annotations

import contextlib
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage

from monotracker.ct.volume import Volume
from monotracker.ui import navigation_panel as navp
from monotracker.ui.slice_panel import SlicePanel

CENTRE = np.array([4.0, -6.0, 10.0])  # LPS mm: the target, the volume's middle
ENTRY = CENTRE + np.array([0.0, -40.0, 30.0])
RADIUS = 4.0  # ball radius, mm
# S1 lies in the axial and coronal planes through the target, S2 in the coronal and sagittal ones,
# S3 farther than 6 mm from every plane (ortho, probe's eye and along path)
SUGGESTED = CENTRE + np.array([[20.0, 0.0, 0.0], [0.0, 0.0, 25.0], [-20.0, -20.0, 25.0]])
EXPECT = {"axial": {"S1"}, "coronal": {"S1", "S2"}, "sagittal": {"S2"}}


@pytest.fixture(scope="module")
def volume():
    """Air (-1000 HU), 1 mm voxels, 100 a side, a 3000 HU ball of RADIUS at each suggestion."""
    n = 100
    img = sitk.Image(n, n, n, sitk.sitkInt16)
    img.SetOrigin(tuple(CENTRE - (n - 1) / 2))
    arr = np.full((n, n, n), -1000, np.int16)
    kk, jj, ii = np.mgrid[0:n, 0:n, 0:n]
    for b in SUGGESTED:
        ci = np.array(img.TransformPhysicalPointToContinuousIndex(tuple(float(v) for v in b)))
        arr[(ii - ci[0]) ** 2 + (jj - ci[1]) ** 2 + (kk - ci[2]) ** 2 <= RADIUS**2] = 3000
    out = sitk.GetImageFromArray(arr)
    out.CopyInformation(img)
    return Volume.from_image(out, "synthetic")


def _snap(layout=True):
    lay = SimpleNamespace(ready=True, balls_lps_mm=SUGGESTED, radius_mm=RADIUS) if layout else None
    return SimpleNamespace(plan=SimpleNamespace(entry_lps_mm=ENTRY, target_lps_mm=CENTRE), fiducials=(),
                           layout=lay, pose=None,
                           scene=SimpleNamespace(T_base_ct=None, T_base_tip=None))


@pytest.fixture
def labels(monkeypatch):
    """Every text drawn with OpenCV, in order (the labels S<k> among them)."""
    said = []
    real = cv2.putText

    def put(img, text, *a, **k):
        said.append(text)
        return real(img, text, *a, **k)

    monkeypatch.setattr(cv2, "putText", put)
    return said


def _suggestion_labels(said):
    return {t for t in said if len(t) > 1 and t[0] == "S" and t[1:].isdigit()}


def _ringed_balls(rgb, ring_px):
    """The white disks of the image (the CT's balls: > 60 px once the crosshair and the centre dot
    drawn over them are closed; the top 30 and bottom 50 rows, where the views write what they show,
    left out)
    and, for each, the share of the pixels on a circle of ``ring_px`` around its centroid that are
    the suggestion's blue."""
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    white = (r > 200) & (g > 200) & (b > 200)
    white[:30] = False
    white[-50:] = False
    lab, n = ndimage.label(ndimage.binary_closing(white, iterations=3))
    blue = (b > 150) & (b - g > 80) & (r < 120)  # the suggestion's blue (RGB 30, 90, 230), not the path's cyan
    out = []
    for i in range(1, n + 1):
        if (lab == i).sum() < 60:
            continue  # text, not a ball
        cy, cx = ndimage.center_of_mass(lab == i)
        a = np.linspace(0, 2 * np.pi, 72, endpoint=False)
        xs = np.clip(np.round(cx + ring_px * np.cos(a)).astype(int), 0, rgb.shape[1] - 1)
        ys = np.clip(np.round(cy + ring_px * np.sin(a)).astype(int), 0, rgb.shape[0] - 1)
        out.append(float(blue[ys, xs].mean()))
    return out


def _blue_pixels(rgb):
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    return int(((b > 150) & (b - g > 80) & (r < 120)).sum())


def _slice_panel(vol, key):
    handles = []

    def add_image(image, label, format):
        handles.append(SimpleNamespace(image=image, label=label))
        return handles[-1]

    view = SimpleNamespace(gui=SimpleNamespace(add_image=add_image), session=SimpleNamespace(volume=lambda: vol),
                           scene_keys={})
    return SlicePanel(view, key), view


def _labels_per_plane(said):
    """The S<k> labels drawn on each plane: a slice's labels come before its "<plane> ..." line."""
    out, bucket = {}, set()
    for t in said:
        if t.split(" ")[0] in EXPECT:
            out[t.split(" ")[0]], bucket = bucket, set()
        elif _suggestion_labels([t]):
            bucket.add(t)
    return out


def test_plan_slices_number_the_suggested_balls_where_the_ct_has_them(volume, labels):
    panel, view = _slice_panel(volume, "plan")
    panel.render(_snap(), CENTRE)
    ring = (RADIUS + 2.0) * 2  # the ring is (radius + 2) mm wide: 1 mm pixels upscaled x2
    for plane, want in EXPECT.items():
        rings = _ringed_balls(panel.handles[plane].image, ring)
        # each ball the CT shows on this plane is circled in blue
        assert len(rings) == len(want) and min(rings) > 0.6, (plane, rings)  # lines drawn across take a part
    assert _labels_per_plane(labels) == EXPECT
    # the layout gone: redrawn (the cache key has the balls), no blue at all
    panel.render(_snap(layout=False), CENTRE)
    assert all(_blue_pixels(h.image) == 0 for h in panel.handles.values())


def test_the_ct_step_slices_show_no_suggestions(volume, labels):
    panel, _ = _slice_panel(volume, "ct")
    panel.render(_snap(), CENTRE)
    assert not _suggestion_labels(labels)
    assert all(_blue_pixels(h.image) == 0 for h in panel.handles.values())


class _Scene:
    def __init__(self):
        self.images = {}

    def reset(self):
        pass

    def add_image(self, name, image, *_a, **_k):
        self.images[name] = image
        h = SimpleNamespace(image=image, on_click=lambda f: f)
        return h


def _nav(vol, key):
    cam = SimpleNamespace(aspect=1.6, image_height=800, fov=0.9, update_timestamp=1.0)
    view = SimpleNamespace(client_id="t", scene=_Scene(), say=lambda ok, msg: None,
                           client=SimpleNamespace(camera=cam, atomic=contextlib.nullcontext),
                           safe=lambda _what: (lambda f: f),
                           session=SimpleNamespace(volume=lambda: vol, config=SimpleNamespace(max_pose_age_s=0.15)))
    sc = navp.NavigationScene(view)
    sc.close()  # no worker: the test renders
    sc._thread.join(5)
    panel = SimpleNamespace(key=key, live=False, state=lambda: (True, 2000.0, 300.0, None),
                            h_info=SimpleNamespace(content=""))
    return view, sc, panel


def test_plan_navigation_views_number_the_suggested_balls(volume, labels):
    view, sc, panel = _nav(volume, "plan")
    sc._request = (_snap(), panel)
    sc._render_once()
    tiles = sc.tiles()
    for plane, want in EXPECT.items():
        v = tiles[plane][0]
        ring = (RADIUS + 2.0) / v.pixel_mm * 2
        rings = _ringed_balls(view.scene.images[f"/nav/{plane}"], ring)
        assert len(rings) == len(want) and min(rings) > 0.6, (plane, rings)  # lines drawn across take a part
    got = _suggestion_labels(labels)
    assert {"S1", "S2"} <= got and "S3" not in got
    # the robot step's navigation views: the balls on the head, not the advice
    labels.clear()
    view, sc, panel = _nav(volume, "robot")
    sc._request = (_snap(), panel)
    sc._render_once()
    assert not _suggestion_labels(labels)
    assert all(_blue_pixels(img) == 0 for img in view.scene.images.values())
