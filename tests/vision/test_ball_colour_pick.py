"""Ball colour from one click in the web UI (ui/ball_colour_pick.py, ui/step_register.py).

Callback level: a fake viser client (camera pose, scene with clickable image nodes) and fake GUI
widgets around a real simulated-clock Session. The click is made the way viser's browser client
makes it: a ray from the viewer's camera through a point of the image node, whose picture
(viser's ThreeAssets.tsx: a plane rotated by pi about x) has columns along the node's +x and rows
along +y. The truth is the simulator's exact ellipse centre of a ball in the full-resolution
frame; the picture sent to the browser is downscaled, so a mapping that ignored that would land
~100 px off the ball and be refused.
"""

from __future__ import annotations

import numpy as np
import pytest

from monotracker.engine import Session, SessionConfig
from monotracker.geometry import look_at
from monotracker.ui.ball_colour_pick import MAX_SEND_WIDTH, BallColourPicker, click_to_pixel, pick_placement


def _wxyz(R):
    """Rotation matrix -> unit quaternion (w, x, y, z)."""
    w = np.sqrt(max(1.0 + np.trace(R), 1e-12)) / 2
    return np.array([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)])


class FakeCamera:
    """A viewer camera at ``eye`` looking at ``target`` (OpenCV convention, as viser's)."""

    def __init__(self, eye, target, fov=0.9, aspect=1.6):
        self.position, self.look_at, self.fov, self.aspect = np.asarray(eye, float), np.asarray(target, float), fov, aspect
        T = look_at(self.position, self.look_at, np.array([0.0, 0.0, 1.0]))
        self.R = T[:3, :3]
        self.wxyz = _wxyz(self.R)


class FakeImageNode:
    def __init__(self, image, rw, rh, wxyz, position):
        self.image, self.rw, self.rh = image, rw, rh
        self.wxyz, self.position = np.asarray(wxyz, float), np.asarray(position, float)
        self.clicks, self.removed = [], False

    def on_click(self, fn):
        self.clicks.append(fn)
        return fn

    def remove(self):
        self.removed = True

    def world_point(self, u, v):
        """World point of picture coordinates u, v in [0, 1] (left->right, top->bottom)."""
        from monotracker.ui.ball_colour_pick import _R

        local = np.array([(u - 0.5) * self.rw, (v - 0.5) * self.rh, 0.0])
        return self.position + _R(self.wxyz) @ local


class FakeScene:
    def __init__(self):
        self.nodes = []

    def add_image(self, name, image, render_width, render_height, *, wxyz, position, **_kw):
        n = FakeImageNode(image, render_width, render_height, wxyz, position)
        self.nodes.append(n)
        return n


class Event:
    def __init__(self, origin, point):
        d = np.asarray(point, float) - origin
        self.ray_origin, self.ray_direction = tuple(origin), tuple(d / np.linalg.norm(d))


class RecordingSession:
    """The real session; learn_ball_colour's arguments are recorded."""

    def __init__(self, s):
        self.s, self.calls = s, []

    def latest_frame(self):
        return self.s.latest_frame()

    def learn_ball_colour(self, x, y, **kw):
        self.calls.append((x, y, kw.get("frame"), kw.get("frame_index")))
        return self.s.learn_ball_colour(x, y, **kw)


class FakeView:
    def __init__(self, session, camera):
        self.session, self.scene, self.lines = session, FakeScene(), []
        self.client = type("Client", (), {"camera": camera})()

    def say(self, ok, text):
        self.lines.append((ok, text))

    def run(self, what, fn, *args):
        r = fn(*args)
        self.say(r.ok, f"{what}: {r.message}")
        return r

    def safe(self, what):
        return lambda fn: fn

    def goto(self, step):
        pass

    def show_step(self):  # the live image over the main view steps aside while a pick waits
        pass


@pytest.fixture
def live(tmp_path):
    from monotracker.sim.phantom import default_phantom

    s = Session(SessionConfig(home=tmp_path / "home", clock="sim"))
    ph = default_phantom()
    for c in ph.fiducial_centres_lps:
        assert s.add_fiducial(c, ph.fiducial_radius_mm).ok
    assert s.confirm_fiducials().ok and s.use_sample_plan().ok
    assert s.start_camera().ok
    s.advance(0.2)
    yield s
    s.shutdown()


def _ball_far_from_the_corner(truth):
    vis = np.flatnonzero(truth.visible)
    k = vis[np.argmax(np.linalg.norm(truth.ellipse_centres_px[vis], axis=1))]
    return k, truth.ellipse_centres_px[k]


def test_placement_faces_the_viewer_and_fills_the_view():
    cam = FakeCamera([400.0, -300.0, 250.0], [0.0, 0.0, 0.0])
    pos, wxyz, rw, rh = pick_placement(cam.position, cam.wxyz, cam.look_at, cam.fov, cam.aspect, (1280, 720))
    d = pos - cam.position
    assert np.allclose(d / np.linalg.norm(d), cam.R[:, 2], atol=1e-9)        # on the optical axis
    dist = np.linalg.norm(d)
    view_h = 2 * dist * np.tan(cam.fov / 2)
    # a 1.6:1 canvas is narrower than the 16:9 picture: it fills 80 % of the view's width
    assert rw == pytest.approx(0.8 * view_h * 1.6) and rw / rh == pytest.approx(1280 / 720)
    wide = pick_placement(cam.position, cam.wxyz, cam.look_at, cam.fov, 2.2, (1280, 720))
    assert wide[3] == pytest.approx(0.8 * view_h)                           # a wide one: 80 % of the height
    # the picture's centre ray and a ray through its corner map back to the right pixels
    node = FakeImageNode(None, rw, rh, wxyz, pos)
    assert click_to_pixel(cam.position, node.world_point(0.5, 0.5) - cam.position, pos, wxyz, rw, rh,
                          (1280, 720)) == pytest.approx((639.5, 359.5))
    x, y = click_to_pixel(cam.position, node.world_point(0.25, 0.75) - cam.position, pos, wxyz, rw, rh, (1280, 720))
    assert (x, y) == pytest.approx((319.5, 539.5))
    # a ray that misses the picture gives no pixel
    assert click_to_pixel(cam.position, node.world_point(1.3, 0.5) - cam.position, pos, wxyz, rw, rh, (1280, 720)) is None
    # screen orientation: image right = the viewer's screen right (+x of the OpenCV camera),
    # image down = screen down (+y)
    assert np.dot(node.world_point(1, 0.5) - node.world_point(0, 0.5), cam.R[:, 0]) > 0
    assert np.dot(node.world_point(0.5, 1) - node.world_point(0.5, 0), cam.R[:, 1]) > 0


def test_click_on_a_ball_learns_its_colour_refusals_are_one_line(live):
    cam = FakeCamera([350.0, -420.0, 380.0], [0.0, 0.0, 60.0])
    rec = RecordingSession(live)
    view = FakeView(rec, cam)
    shown = []
    picker = BallColourPicker(view, on_result=shown.append)
    rig = live._loop.camera.rig
    img = live.latest_frame()[0]
    truth = rig._last_frame.truth
    H, W = img.shape[:2]
    assert W > MAX_SEND_WIDTH                                    # the picture is downscaled

    assert picker.start()
    node = view.scene.nodes[-1]
    assert node.image.shape[1] == MAX_SEND_WIDTH and node.clicks
    # a click beside the picture: nothing learned, the pick stays open
    node.clicks[0](Event(cam.position, node.world_point(1.2, 0.5)))
    assert not rec.calls and not node.removed and "off the camera image" in shown[-1]

    k, (x, y) = _ball_far_from_the_corner(truth)
    node.clicks[0](Event(cam.position, node.world_point((x + 0.5) / W, (y + 0.5) / H)))
    assert node.removed and len(rec.calls) == 1
    assert np.allclose(rec.calls[0][:2], (x, y), atol=0.05)
    assert view.lines[-1][0], view.lines[-1]
    col = rig.tracker.detector.colour
    assert col is not None and col.hue_lo < 60 < col.hue_hi                # the balls are green (hue ~58)
    assert "hue" in shown[-1] and "\n" not in shown[-1]

    # a click on the drape (picture corner): refused in one line, the learned colour stays
    assert picker.start()
    node = view.scene.nodes[-1]
    node.clicks[0](Event(cam.position, node.world_point(0.01, 0.02)))
    assert not view.lines[-1][0] and "\n" not in view.lines[-1][1]
    assert shown[-1].startswith("NOT LEARNED")
    assert rig.tracker.detector.colour == col


def test_the_click_learns_from_the_shown_frame_never_a_newer_one(live, monkeypatch):
    """Frame A is shown; before the click the camera's newest frame becomes one where the
    clicked pixel is drape (the head moved). The colour is learned from A, never from the newer
    frame (the engine side's refusal by frame index is in tests/engine/test_ball_colour_cmd.py)."""
    cam = FakeCamera([350.0, -420.0, 380.0], [0.0, 0.0, 60.0])
    rec = RecordingSession(live)
    view = FakeView(rec, cam)
    shown = []
    picker = BallColourPicker(view, on_result=shown.append)
    rig = live._loop.camera.rig
    img_a, idx_a, _ = live.latest_frame()
    H, W = img_a.shape[:2]
    k, (x, y) = _ball_far_from_the_corner(rig._last_frame.truth)
    assert picker.start()
    node = view.scene.nodes[-1]

    drape = np.empty_like(img_a)
    drape[:] = img_a[3, 3]
    monkeypatch.setattr(rig, "latest_frame", lambda: (drape, idx_a + 1, None))
    node.clicks[0](Event(cam.position, node.world_point((x + 0.5) / W, (y + 0.5) / H)))
    assert node.removed
    assert len(rec.calls) == 1 and rec.calls[0][2] is img_a and rec.calls[0][3] == idx_a
    assert view.lines[-1][0], view.lines[-1]
    col = rig.tracker.detector.colour
    assert col is not None and col.hue_lo < 60 < col.hue_hi                # green balls of frame A


def test_no_frame_yet_is_one_line(tmp_path):
    s = Session(SessionConfig(home=tmp_path / "h", clock="sim"))
    try:
        view = FakeView(RecordingSession(s), FakeCamera([0.0, -500.0, 0.0], [0.0, 0.0, 0.0]))
        assert not BallColourPicker(view).start()
        assert not view.lines[-1][0] and "start the camera" in view.lines[-1][1] and not view.scene.nodes
    finally:
        s.shutdown()


class FakeWidget:
    def __init__(self, label, value=None):
        self.label, self.value, self.callbacks, self.content = label, value, [], ""

    def on_click(self, fn):
        self.callbacks.append(fn)
        return fn

    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


class FakeGui:
    def __init__(self):
        self.widgets = {}

    def __getattr__(self, name):
        if not name.startswith("add_"):
            raise AttributeError(name)

        def add(*args, **kw):
            label = kw.get("label") or (args[0] if args and isinstance(args[0], str) else "")
            w = FakeWidget(label, kw.get("initial_value", args[1] if len(args) > 1 else None))
            self.widgets[label] = w
            return w

        return add


def test_register_step_wires_the_pick_and_the_typed_pixel(live):
    from monotracker.ui.step_register import RegisterStep

    cam = FakeCamera([350.0, -420.0, 380.0], [0.0, 0.0, 60.0])
    rec = RecordingSession(live)
    view = FakeView(rec, cam)
    view.gui = FakeGui()
    rec.config = live.config
    step = RegisterStep(view)
    truth = live._loop.camera.rig._last_frame.truth
    k, (x, y) = _ball_far_from_the_corner(truth)
    # typed pixel
    view.gui.widgets["Ball at x, y (px)"].value = (float(x), float(y))
    view.gui.widgets["Learn ball colour at x, y"].callbacks[0](None)
    assert rec.calls[-1][:2] == (float(x), float(y)) and view.lines[-1][0], view.lines[-1]
    assert "hue" in step.h_colour.content
    # pick mode from the button group, then Cancel removes the picture
    grp = view.gui.widgets["Ball colour"]
    ev = type("E", (), {"target": type("T", (), {"value": "Learn ball colour (click a ball)"})()})()
    grp.callbacks[0](ev)
    node = view.scene.nodes[-1]
    assert step.picker.active and not node.removed
    ev.target.value = "Cancel"
    grp.callbacks[0](ev)
    assert node.removed and not step.picker.active


def test_the_real_viser_scene_takes_the_pick_node(live):
    """The calls the picker makes exist in the pinned viser (1.1.x): a scene image node with a
    click callback (GUI images have none)."""
    import socket

    import viser

    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        port = sk.getsockname()[1]
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    try:
        view = FakeView(RecordingSession(live), FakeCamera([350.0, -420.0, 380.0], [0.0, 0.0, 60.0]))
        view.scene = server.scene
        picker = BallColourPicker(view)
        assert picker.start(), view.lines
        node = picker._node
        assert isinstance(node, viser.ImageHandle) and len(node._impl.click_cb) == 1
        assert not hasattr(viser.GuiImageHandle, "on_click")
        picker.cancel()
        assert not picker.active
    finally:
        server.stop()
