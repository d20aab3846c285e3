"""The shared overlay stream draws on the frame already downscaled for display: every mark lands
where the camera-pixel truth says it should (scaled), as when drawing on the full frame first."""

from __future__ import annotations

from types import SimpleNamespace as NS

import cv2
import numpy as np


def _scene():
    K = np.array([[900.0, 0, 640], [0, 900.0, 360], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0, 0, 400.0]
    centres = np.array([[0.0, 0, 0], [60, 0, 0], [0, 60, 0], [-60, -30, 0]])
    fids = tuple(NS(id=i, centre_lps_mm=c, radius_mm=4.0, status="confirmed") for i, c in enumerate(centres))
    status = {0: "seen", 1: "seen", 2: "seen", 3: "occluded"}
    pose = NS(trusted=True, reason="", T_cam_ct=T, fiducial_status=status, residuals_px={}, fre_mm=0.1,
              predicted_tre_mm=0.5)
    snap = NS(pose=pose, camera=NS(K=K, dist=None), fiducials=fids, plan=NS(entry_lps_mm=None, target_lps_mm=None))
    return K, T, centres, status, snap


def test_marks_at_display_scale_match_camera_pixels():
    from monotracker.ui.overlay import GREEN, RED, project_points
    from monotracker.ui.stream import OverlayStream

    K, T, centres, status, snap = _scene()
    uv = project_points(centres, T, K)  # camera px (1280x720 frame), hand-checkable: 640 + 900*x/400
    assert np.allclose(uv[1], [640 + 900 * 60 / 400, 360])
    est = NS(T_cam_ct=T, status=list(status.values()), image_points_px=uv, residuals_px=np.full(4, np.nan))
    frame = np.full((720, 1280, 3), 90, np.uint8)
    stream = OverlayStream(display_width=640)
    out = cv2.imdecode(np.frombuffer(stream.encode_frame(frame, est, snap), np.uint8), cv2.IMREAD_COLOR)
    assert out.shape == (360, 640, 3)
    s = 0.5
    for j in (0, 1, 2):  # a green dot at each detected centre, scaled to the display
        u, v = np.round(uv[j] * s).astype(int)
        patch = out[v - 1:v + 2, u - 1:u + 2].reshape(-1, 3).astype(int)
        assert np.all(np.abs(patch - GREEN).max(axis=1) < 60), (j, patch)
    u, v = np.round(uv[3] * s).astype(int)  # the hidden one: a red ring around its place, not a dot
    ring = out[v - 12:v + 13, u - 12:u + 13].reshape(-1, 3).astype(int)
    assert np.any(np.abs(ring - RED).max(axis=1) < 60)
    assert np.abs(out[v, u].astype(int) - GREEN).max() > 60
    assert frame.mean() == 90  # the camera frame itself is never drawn on


def test_banner_and_panel_come_from_one_snapshot(tmp_path, port):
    """The overlay's banner is drawn from the very snapshot the panels were rendered from (the
    render thread's), never from a newer one that could disagree with the panel for a frame."""
    import time

    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp

    s = Session(SessionConfig(home=tmp_path, arm_pin="2468"))
    app = MonoTrackerApp(s, "127.0.0.1", port)
    rendered, drawn = [], []

    class FakeTab:  # a tab on the Register step (what the render and overlay threads see of it)
        client_id = "fake"
        client = None  # unreadable buffer: the overlay never waits on it
        wants_live = True

        def render(self, snap):
            rendered.append(snap)

        def show_frame(self, data):
            pass

        def close(self):
            pass

    real_encode = app.stream.encode_frame

    def encode(image, est, snap, **kw):
        drawn.append(snap)
        return real_encode(image, est, snap, **kw)

    app.stream.encode_frame = encode
    frame = np.full((720, 1280, 3), 90, np.uint8)
    k = [0]

    def latest_frame():
        k[0] += 1
        return frame, k[0], None

    s.latest_frame = latest_frame
    app._views["fake"] = FakeTab()
    app.start()
    try:
        t0 = time.monotonic()
        while len(drawn) < 20 and time.monotonic() - t0 < 120:
            time.sleep(0.05)
    finally:
        app.stop()
        s.shutdown()
    assert len(drawn) >= 20
    ids = {id(x) for x in rendered}
    assert all(id(x) in ids for x in drawn[1:])  # (the first frame may precede the first render)


def test_one_encode_per_display_width_shared_by_tabs(tmp_path, port):
    """Tabs that show the live image at the same width share one JPEG (the same bytes); a tab
    with a wider panel gets its own, at its width; no tab gets more pixels than it shows."""
    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp

    s = Session(SessionConfig(home=tmp_path, arm_pin="2468"))
    app = MonoTrackerApp(s, "127.0.0.1", port, display_width=960)
    got = {}

    class FakeTab:
        wants_live = True

        def __init__(self, name, width):
            self.name, self.live_width = name, width

        def show_frame(self, data):
            got[self.name] = data

    tabs = [FakeTab("a", 480), FakeTab("b", 640), FakeTab("c", 480), FakeTab("d", 2000)]
    calls = []
    real_encode = app.stream.encode_frame

    def encode(image, est, snap, width=None):
        calls.append(width)
        return real_encode(image, est, snap, width=width)

    app.stream.encode_frame = encode
    try:
        frame = np.full((720, 1280, 3), 90, np.uint8)
        out = app.push_frame(frame, None, s.snapshot(), tabs)
    finally:
        s.shutdown()
    assert sorted(calls) == [480, 640, 960]  # one encode per width; 2000 px capped at display_width
    assert got["a"] is got["c"]  # the very same buffer for both 480 px tabs
    for name, w in (("a", 480), ("b", 640), ("d", 960)):
        img = cv2.imdecode(np.asarray(got[name]), cv2.IMREAD_COLOR)
        assert img.shape == (round(720 * w / 1280), w, 3)
    assert set(out) == {480, 640, 960}


def test_frame_comment_leaves_the_image_unchanged():
    """The benchmark's frame number rides in a JPEG comment: decoders give the same pixels and a
    third-party reader (Pillow) finds the comment."""
    import io

    from PIL import Image

    from monotracker.ui.stream import with_frame_comment

    img = (np.random.default_rng(1).random((48, 64, 3)) * 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img)
    plain = buf.tobytes()
    tagged = with_frame_comment(plain, 98765)
    a = cv2.imdecode(np.frombuffer(plain, np.uint8), cv2.IMREAD_COLOR)
    b = cv2.imdecode(np.frombuffer(tagged, np.uint8), cv2.IMREAD_COLOR)
    assert np.array_equal(a, b)
    im = Image.open(io.BytesIO(tagged))
    im.load()
    assert im.info.get("comment") == b"MTFRAME 98765"
