"""The surgeon's screen at view level (issue 33): live figures are never stale numbers, the
overlay's labels never overlap and its banner is never cut, the camera-stopped view."""

from __future__ import annotations

from types import SimpleNamespace as NS

import numpy as np
import pytest


# ---------------------------------------------------------------- snapshots for the figures
def _snap(*, t=100.0, pose_t=99.95, trusted=True, reason="", state="tracking", connected=True, running=True,
          errors_t=99.95, command_t=99.96, tip=1.64, angle=1.02):
    pose = NS(t=pose_t, trusted=trusted, reason=reason, fre_mm=0.21, predicted_tre_mm=0.4, latency_ms=30.0,
              n_visible=6, trusted_t=errors_t, fiducial_status={1: "seen", 2: "occluded"},
              residuals_px={1: 0.12, 2: float("nan")}, validation_ok=None)
    robot = NS(state=state, connected=connected, tip_error_mm=tip, angle_error_deg=angle, speed_mm_s=3.0,
               latency_ms=12.0, errors_t=errors_t, command_t=command_t, message="ok")
    camera = NS(running=running, error=None, source="sim", fps=30.0)
    return NS(t=t, pose=pose, robot=robot, camera=camera, recording=None)


def _numbers(html: str) -> bool:
    import re

    return re.search(r"\d+\.\d+ mm|\d+\.\d+&deg;", html) is not None


def test_robot_figures_live_with_their_age():
    from monotracker.ui.step_robot import robot_info_html

    html = robot_info_html(_snap(), wall_of=lambda t: 1_700_000_000.0 + t)
    assert "1.64 mm" in html and "1.02&deg;" in html
    assert "id='mt-fig-tip' data-live='1' data-age='0.050'" in html
    assert "50 ms old" in html  # the age shown beside the number


@pytest.mark.parametrize("case", ["occluded", "estop", "old", "camera_stopped", "disconnected"])
def test_no_tip_or_angle_error_shown_as_live_without_a_trusted_fresh_source(case):
    """Every fiducial occluded, an e-stop, a pose 3 s old, the camera stopped: the tip and
    angle error are blanked, with "stale since <clock>" and why; the number is not on the page."""
    from monotracker.ui.step_robot import robot_info_html

    kw = {"occluded": dict(trusted=False, reason="occlusion: 0 fiducials seen", state="holding"),
          "estop": dict(state="estopped"),
          "old": dict(t=103.0),
          "camera_stopped": dict(running=False, state="holding"),
          "disconnected": dict(connected=False)}[case]
    html = robot_info_html(_snap(**kw), wall_of=lambda t: 1_700_000_000.0 + t)
    assert "id='mt-fig-tip' data-live='0'" in html and "id='mt-fig-angle' data-live='0'" in html
    assert not _numbers(html.split("id='mt-fig-speed'")[0]), html  # no mm / deg figure before speed
    assert "stale since" in html
    why = {"occluded": "occlusion", "estop": "e-stopped", "old": "3.0 s old", "camera_stopped": "camera stopped",
           "disconnected": "not connected"}[case]
    assert why in html


def test_latency_is_stale_when_no_command_is_sent():
    from monotracker.ui.freshness import robot_figures

    assert robot_figures(_snap())["latency"].live
    f = robot_figures(_snap(state="holding"))["latency"]
    assert not f.live and "holding" in f.why


def test_register_banner_table_and_status_line_blank_an_untrusted_pose():
    from monotracker.ui.status import pose_line
    from monotracker.ui.step_register import pose_banner, registration_table

    wall = lambda t: 1_700_000_000.0 + t
    good = _snap()
    assert "0.21 mm" in pose_banner(good, wall) and "data-live='1'" in pose_banner(good, wall)
    assert "0.21 mm" in pose_line(good)
    assert "data-live='1'" in registration_table(good.pose, good, wall)
    for bad in (_snap(trusted=False, reason="occlusion: 2 fiducials seen"), _snap(t=105.0)):
        banner = pose_banner(bad, wall)
        assert "0.21 mm" not in banner and "0.40 mm" not in banner and "stale since" in banner
        assert "0.21 mm" not in pose_line(bad) and "NOT VALID" in pose_line(bad)
        table = registration_table(bad.pose, bad, wall)
        assert "data-live='0'" in table and "residuals stale since" in table
    stopped = _snap(running=False)
    assert "camera stopped" in pose_banner(stopped, wall) and "0.21 mm" not in pose_line(stopped)


def test_a_pose_read_from_a_still_views_mean_says_so_on_the_screen():
    """The opt-in still-view mean (``serve --average-still-frames``): a valid pose whose detector
    read the mean of 6 still frames says so in the register banner and the status line; one read
    from its frame alone, or not valid, says nothing of it."""
    from monotracker.ui.status import pose_line
    from monotracker.ui.step_register import pose_banner

    wall = lambda t: 1_700_000_000.0 + t
    snap = _snap()
    assert "mean of" not in pose_line(snap) and "mean of" not in pose_banner(snap, wall)
    snap.pose.averaged_frames = 6
    assert "read from the mean of 6 still frames" in pose_line(snap)
    assert "read from the mean of 6 still frames" in pose_banner(snap, wall)
    snap.pose.averaged_frames = 1
    assert "mean of" not in pose_line(snap)
    bad = _snap(trusted=False, reason="occlusion: 2 fiducials seen")
    bad.pose.averaged_frames = 6
    assert "mean of" not in pose_line(bad)


# ---------------------------------------------------------------- the overlay's labels
def _sample_scene(crowd: float = 1.0):
    """The sample phantom seen by the simulated camera at rest: its 9 fiducials (and the sample
    path), the camera's K, the true T_cam_ct. ``crowd`` < 1 squeezes the balls together in the
    image (about their centroid) to make the labels' job harder."""
    from monotracker.sim.camera_sim import SimulatedCamera

    cam = SimulatedCamera()
    ph = cam.phantom
    T = cam.T_cam_ct_at(0.0)
    uv = cam.rest_projection()
    uv = uv.mean(axis=0) + (uv - uv.mean(axis=0)) * crowd
    ids = list(range(len(uv)))
    states = ["seen"] * len(ids)
    states[2], states[5], states[7] = "occluded", "moved", "unknown"
    fids = tuple(NS(id=i, centre_lps_mm=c, radius_mm=4.0, status="confirmed") for i, c in zip(ids, ph.fiducial_centres_lps))
    pose = NS(trusted=True, reason="", T_cam_ct=T, fiducial_status=dict(zip(ids, states)),
              residuals_px={i: 0.01 * (i + 1) for i in ids}, fre_mm=0.12, predicted_tre_mm=0.35)
    snap = NS(pose=pose, camera=NS(K=cam.K, dist=cam.dist), fiducials=fids,
              plan=NS(entry_lps_mm=ph.sample_entry_lps, target_lps_mm=ph.sample_target_lps))
    pts = uv.copy()
    pts[[2, 5, 7]] = np.nan  # not detected in this frame
    est = NS(T_cam_ct=T, status=states, image_points_px=pts, residuals_px=np.array([0.01 * (i + 1) for i in ids]))
    return cam.camera.image_size, est, snap


@pytest.mark.parametrize("width", [480, 640, 960, 1280])
@pytest.mark.parametrize("crowd", [1.0, 0.25])
def test_overlay_labels_never_intersect_at_any_display_width(width, crowd):
    """The sample scene drawn at the widths the page shows it: no two label boxes (the banner
    included) intersect, each lies inside the image, and each box really holds its text (the
    drawn pixels of the labels lie inside the boxes: the boxes are not just bookkeeping)."""
    from monotracker.ui.overlay import draw_overlay
    from monotracker.ui.stream import OverlayStream

    (w, h), est, snap = _sample_scene(crowd)
    frame = np.zeros((h, w, 3), np.uint8)
    small = OverlayStream(display_width=width).downscale(frame, width)
    boxes: list = []
    out = draw_overlay(small, est, snap, px_scale=small.shape[1] / w, label_boxes=boxes)
    assert len(boxes) == 1 + 9  # the banner and one label per ball
    for i, a in enumerate(boxes):
        assert 0 <= a[0] < a[2] <= out.shape[1] and 0 <= a[1] < a[3] <= out.shape[0], a
        for b in boxes[i + 1:]:
            assert not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]), (width, a, b)
    # the banner holds its whole message: one or two lines, nothing cut at the right edge
    assert out[boxes[0][1]:boxes[0][3], -3:].reshape(-1, 3).max(axis=1).min() < 250


def test_banner_wraps_instead_of_being_cut():
    from monotracker.ui.overlay import _text_box, wrap_banner

    msg = "POSE NOT VALID: predicted error at the target 1.42 mm exceeds the 1.00 mm limit   (predicted TRE 1.42 mm)"
    for width in (440, 480, 640):
        lines, scale = wrap_banner(msg, width - 16, 0.75, 1)
        assert " ".join(lines).split() == msg.split() and len(lines) <= 2
        assert all(_text_box(ln, scale, 1)[0] <= width - 16 for ln in lines)
        assert scale >= 0.42


def test_place_labels_crowded_cluster_goes_to_legend_without_overlap():
    from monotracker.ui.overlay import place_labels

    anchors = [(200.0 + i, 150.0 + i) for i in range(12)]  # 12 balls within 12 px
    boxes = place_labels(anchors, [(70, 16)] * 12, 480, 270, avoid=[(0, 0, 480, 30)], gap=10)
    for i, a in enumerate(boxes):
        assert a[1] >= 30 and a[2] <= 480 and a[3] <= 270
        for b in boxes[i + 1:]:
            assert not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3])


def test_ball_states_differ_in_shape_and_colour():
    from monotracker.ui.overlay import BALL_STYLE, ball_state

    assert ball_state("seen", True) == "seen" and ball_state("seen", False) == "predicted"
    assert ball_state("unknown", False) == "predicted" and ball_state("occluded", False) == "lost"
    assert ball_state("newly_lost", True) == "lost" and ball_state("moved", True) == "moved"
    assert ball_state("seen", True, set_aside=True) == "aside" and ball_state("seen", False, True) == "predicted"
    n = len(BALL_STYLE)
    assert n == 5 and len({v[0] for v in BALL_STYLE.values()}) == n and len({v[1] for v in BALL_STYLE.values()}) == n


def test_a_ball_set_aside_is_drawn_where_found_and_labelled_with_its_disagreement():
    """The estimate left ball 4 out of its pose (found 2.1 px from where the others put it): its
    label says so, and a yellow triangle is drawn at its detection (the cyan ring, where the
    others put it, beside it); the other seen balls keep their residual labels; the banner
    counts it apart from the balls the pose used."""
    from monotracker.ui.overlay import BALL_STYLE, draw_overlay

    (w, h), est, snap = _sample_scene()
    est.image_points_px[4] = est.image_points_px[4] + [6.0, 0.0]   # found off its reprojection
    snap.pose.set_aside = {4: 2.1}
    img = np.zeros((h, w, 3), np.uint8)
    boxes: list = []
    texts = []
    import monotracker.ui.overlay as ov
    real = ov._text
    ov._text = lambda image, text, *a, **k: (texts.append(text), real(image, text, *a, **k))[1]
    try:
        out = draw_overlay(img, est, snap, label_boxes=boxes)
    finally:
        ov._text = real
    assert "4 set aside 2.1 px" in texts and "0 0.01 px" in texts, texts
    assert "fiducials 5/9 (1 more set aside)" in " ".join(texts), texts[:2]   # 6 seen, one of them aside
    x, y = np.round(est.image_points_px[4]).astype(int)
    patch = out[y - 20:y + 20, x - 20:x + 20].reshape(-1, 3)
    assert (np.abs(patch.astype(int) - BALL_STYLE["aside"][0]).sum(axis=1) < 40).sum() > 20


def test_camera_stopped_view_dims_the_last_frame_and_says_so():
    from monotracker.ui.overlay import draw_camera_stopped

    last = np.full((270, 480, 3), 200, np.uint8)
    out = draw_camera_stopped(last, 480, 270, "CAMERA STOPPED since 12:03:07")
    assert out.shape == last.shape and np.median(out) < 80  # dimmed
    assert (np.abs(out.astype(int) - [80, 80, 255]).max(axis=2) < 40).sum() > 200  # the red words


# ---------------------------------------------------------------- step buttons, stations, small things
class _Button:
    def __init__(self):
        self.label, self.color = "x", "green"


def test_go_on_buttons_are_green_only_when_their_precondition_holds():
    from monotracker.ui.step_plan import PLAN_GATE, gate
    from monotracker.ui.step_register import REGISTER_GATE

    b = _Button()
    gate(b, False, REGISTER_GATE)
    assert b.color == "gray" and "needs a valid pose" in b.label
    gate(b, True, REGISTER_GATE)
    assert b.color == "green" and b.label == "Registration is good: go to Robot"
    gate(b, False, PLAN_GATE)
    assert b.color == "gray" and "set the entry and the target" in b.label


def _view(client_id="1"):
    from monotracker.ui.view import ClientView

    v = ClientView.__new__(ClientView)
    import threading

    v.lock = threading.RLock()
    v.client_id = client_id
    v.app = NS(last_stop=None)
    v._seen_control, v._seen_state = None, "tracking"
    return v


def _ctl(controller, label="", state="tracking"):
    return NS(control=NS(controller=controller, controller_label=label), robot=NS(state=state))


def test_every_station_is_told_when_control_moves_and_where_stop_was_pressed():
    import time

    v = _view("1")
    assert v.changes_elsewhere(_ctl("1", "station at 10.0.0.5 (tab 1)")) == []  # its own claim: its own result line
    lines = v.changes_elsewhere(_ctl("2", "station at 10.0.0.7 (tab 2)"))
    assert lines == [(False, "Control moved to station at 10.0.0.7 (tab 2): this station is now viewing "
                             "(Take control with the PIN)")]
    other = _view("3")
    assert other.changes_elsewhere(_ctl("2", "OR-2"))[0] == (True, "Control moved: OR-2 is in control now")
    other.app.last_stop = ("2", "station at 10.0.0.7 (tab 2)", time.time())
    stop = other.changes_elsewhere(_ctl("2", "OR-2", state="estopped"))
    assert len(stop) == 1 and not stop[0][0] and "STOP pressed at station at 10.0.0.7 (tab 2)" in stop[0][1]
    assert other.changes_elsewhere(_ctl("2", "OR-2", state="estopped")) == []  # said once
    me = _view("2")
    me._seen_control = "2"
    me.app.last_stop = other.app.last_stop
    assert me.changes_elsewhere(_ctl("2", state="estopped")) == []  # the pressing tab has its own result


def test_a_tab_that_closes_while_it_is_drawn_is_left_alone():
    """The render thread drew on a tab whose browser had just closed it: viser warned of every
    message queued on the closed connection ("Queued a GuiUpdateMessage on a closed connection"),
    log noise in an OR. Now a closed tab is not drawn on, also when it closes between the parts
    of one render, and no overlay frame is shown on it. Truth: the parts' own call records."""
    calls = []
    v = _view("1")
    v.closed = False
    v.step = v._last_session_step = "register"
    v._job_watch, v._last_image_size, v.notice = False, None, None
    v.show_step = lambda: calls.append("step bar")
    v.nav_scene = NS(close=lambda: calls.append("nav closed"))
    v.app = NS(last_stop=None, session=NS(release_control=lambda cid: calls.append(f"release {cid}")))

    def status_render(snap, step):
        calls.append("status")
        v.close()   # the browser closes the tab while the status panel is drawn

    v.status = NS(render=status_render)
    v.steps = {"register": NS(render=lambda snap: calls.append("register panel"), show_frame=calls.append)}
    v.scene3d = NS(render=lambda snap, step: calls.append("3D view"))
    v.live = NS(show_frame=lambda jpeg: calls.append("live"))
    snap = NS(step="register", job=None, camera=NS(image_size=(1280, 720)), robot=NS(state="disarmed"),
              control=NS(controller=None, controller_label=""))
    v.render(snap)
    assert calls == ["step bar", "status", "nav closed", "release 1"], calls
    v.render(snap)
    v.show_frame(b"jpeg")
    assert calls == ["step bar", "status", "nav closed", "release 1"], calls   # nothing more drawn
    # viser has closed the connection and dropped the client, but not yet run the disconnect
    # callback (its thread pool, later under load): nothing is drawn either
    calls.clear()
    clients = {7: object()}
    v.closed, v.client = False, NS(client_id=7)
    v.status = NS(render=lambda snap, step: (calls.append("status"), clients.clear()))
    v.app = NS(last_stop=None, server=NS(get_clients=lambda: dict(clients)))
    v.render(snap)
    v.render(snap)
    v.show_frame(b"jpeg")
    assert calls == ["step bar", "status"], calls


def test_a_gone_tab_gets_no_result_line():
    """The render thread's first half says what changed elsewhere (control moved, STOP pressed at
    another station) before its parts are drawn: said to a tab that had just closed, each line
    earned viser's "closed connection" warning. Now say() leaves a gone tab alone, and a live one
    gets its line. Truth: the result line's content."""
    v = _view("1")
    v._msg_seq = 0
    v.status = NS(h_msg=NS(content="before"))
    clients = {7: object()}
    v.closed, v.client = False, NS(client_id=7)
    v.app = NS(last_stop=None, server=NS(get_clients=lambda: dict(clients)))
    v.say(True, "control moved to station 2")
    assert "control moved to station 2" in v.status.h_msg.content
    v.status.h_msg.content = "before"
    clients.clear()   # viser dropped the connection; its disconnect callback has not run yet
    v.say(False, "STOP pressed at station 2")
    assert v.status.h_msg.content == "before"
    v.closed = True
    v.say(False, "late line")
    assert v.status.h_msg.content == "before"


def test_station_label_is_the_address():
    from monotracker.ui.view import station_label

    conn = NS(remote_address=("10.0.0.5", 51234))
    app = NS(server=NS(_websock_server=NS(_live_connections={7: conn})))
    assert station_label(app, 7) == "station at 10.0.0.5 (tab 7)"
    assert station_label(NS(), 3) == "station 3"


def test_slice_position_reads_as_a_reader_says_it_and_letters_follow_the_axes():
    from monotracker.ui.slices import edge_letters, position_text

    assert position_text("sagittal", [-6.2, 0, 0]) == "sagittal R 6.2 mm"
    assert position_text("sagittal", [6.2, 0, 0]) == "sagittal L 6.2 mm"
    assert position_text("axial", [0, 0, -12.0]) == "axial I 12.0 mm"
    assert position_text("coronal", [0, -3.14, 0]) == "coronal A 3.1 mm"
    # radiological convention (module doc of ui/slices.py), hand-checked
    assert edge_letters("axial") == {"right": "L", "left": "R", "bottom": "P", "top": "A"}
    assert edge_letters("coronal") == {"right": "L", "left": "R", "bottom": "I", "top": "S"}
    assert edge_letters("sagittal") == {"right": "P", "left": "A", "bottom": "I", "top": "S"}


def test_a_target_10_mm_under_the_entry_gets_a_warning():
    from monotracker.ui.step_plan import plan_info

    def snap(length):
        e = np.zeros(3)
        t = np.array([0.0, 0.0, length])
        return NS(plan=NS(entry_lps_mm=e, target_lps_mm=t, complete=True, path_length_mm=length,
                          angle_to_skin_normal_deg=5.0, distance_to_fiducials_mm=20.0), fiducials=())

    assert "mt-shallow" in plan_info(snap(9.5)) and "9.5 mm under the entry" in plan_info(snap(9.5))
    assert "mt-shallow" in plan_info(snap(10.0))
    assert "mt-shallow" not in plan_info(snap(35.0))


def test_reload_ct_offered_only_for_a_restored_plan_without_its_ct():
    from monotracker.ui.step_ct import needs_ct_reload

    assert needs_ct_reload(NS(ct=None, plan_ct_path="/data/ct.nii.gz", job=None))
    assert not needs_ct_reload(NS(ct=None, plan_ct_path="/data/ct.nii.gz", job=NS(done=False)))
    assert not needs_ct_reload(NS(ct=NS(), plan_ct_path="/data/ct.nii.gz", job=None))
    assert not needs_ct_reload(NS(ct=None, plan_ct_path=None, job=None))


def test_a_stopped_camera_replaces_the_last_overlay_with_camera_stopped():
    """The overlay thread (``MonoTrackerApp._overlay_loop``) with a camera that is not running:
    the watching tab gets the last frame dimmed with "CAMERA STOPPED since ...", never the last
    overlay left up as if live."""
    import threading

    import cv2

    from monotracker.ui.app import MonoTrackerApp
    from monotracker.ui.stream import OverlayStream

    shown = []
    got = threading.Event()
    tab = NS(wants_live=True, live_width=480, show_frame=lambda data: (shown.append(bytes(data)), got.set()))
    last = np.full((720, 1280, 3), 200, np.uint8)
    fake = NS(_stop=threading.Event(), max_stream_fps=30.0, MAX_HOLD_S=0.25, stream=OverlayStream(display_width=960),
              views=lambda: [tab], session=NS(latest_frame=lambda: (last, 41, None)),
              shown_snapshot=lambda: NS(camera=NS(running=False)))
    fake.push_stopped = lambda since, tabs: MonoTrackerApp.push_stopped(fake, since, tabs)
    fake.push_jpeg = lambda jpeg, tabs=None: MonoTrackerApp.push_jpeg(fake, jpeg, tabs)
    fake.push_frame = lambda *a, **k: pytest.fail("a stopped camera's frame drawn as live")
    th = threading.Thread(target=MonoTrackerApp._overlay_loop, args=(fake,), daemon=True)
    th.start()
    try:
        assert got.wait(60)
    finally:
        fake._stop.set()
        th.join(10)
    img = cv2.imdecode(np.frombuffer(shown[0], np.uint8), cv2.IMREAD_COLOR)
    assert img.shape[1] == 480 and np.median(img) < 80  # the last frame, dimmed, at the tab's width
    assert (np.abs(img.astype(int) - [80, 80, 255]).max(axis=2) < 60).sum() > 100  # the red words


# ---------------------------------------------------------------- the live image's cost
def test_overlay_text_from_the_sprite_cache_is_what_puttext_draws():
    """The overlay's texts are drawn from cached anti-aliased masks (cheap when a text repeats):
    the pixels are those of OpenCV's two ``putText`` calls (black outline, then the colour), also
    a second time (from the cache) and clipped at the image's edges."""
    import cv2

    from monotracker.ui import overlay as ov

    rng = np.random.default_rng(3)
    base = rng.integers(0, 255, (90, 420, 3)).astype(np.uint8)
    for text, org, colour, scale, thick in (("POSE OK   FRE 0.12 mm", (8, 40), (255, 255, 255), 0.95, 2),
                                            ("7 0.04 px", (300, 80), (60, 200, 60), 0.45, 1),
                                            ("cut at the right edge", (330, 20), (40, 40, 235), 0.7, 2),
                                            ("cut at the top", (-6, 6), (255, 220, 0), 0.7, 2)):
        ref = base.copy()
        cv2.putText(ref, text, org, ov.FONT, scale, (0, 0, 0), thick + 3, cv2.LINE_AA)
        cv2.putText(ref, text, org, ov.FONT, scale, colour, thick, cv2.LINE_AA)
        for _ in range(2):  # drawn, then from the cache
            img = base.copy()
            ov._text(img, text, org, colour, scale, thick)
            # (OpenCV's own anti-aliasing differs on the image's outermost pixels: left out)
            diff = np.abs(img.astype(int) - ref.astype(int))[1:-1, 1:-1]
            assert diff.max() <= 6 and diff.mean() < 0.5, (text, diff.max(), diff.mean())  # AA rounding only


def test_a_tab_with_the_live_image_unticked_gets_no_frames():
    """Register / Robot with **Live image in the main view** unticked (or the slices in the main
    view, or a ball-colour pick waiting): no frame is encoded or sent to that tab (the overlay
    thread asks ``wants_live``); Calibrate always shows it."""
    import threading

    from monotracker.ui.view import ClientView

    def tab(step, ticked, steps=None):
        view = NS(lock=threading.RLock(), step=step, h_live_main=NS(value=ticked), steps=steps or {})
        view.live_main_wanted = lambda: ClientView.live_main_wanted(view)
        return view

    assert ClientView.wants_live.fget(tab("register", True))
    assert not ClientView.wants_live.fget(tab("register", False))
    assert not ClientView.wants_live.fget(tab("robot", False))
    assert ClientView.wants_live.fget(tab("calibration", False))
    assert not ClientView.wants_live.fget(tab("ct", True))
    # it steps aside for the navigation slices in the main view and for a ball-colour pick
    assert not ClientView.wants_live.fget(tab("robot", True, {"robot": NS(nav=NS(active=True))}))
    assert ClientView.wants_live.fget(tab("robot", True, {"robot": NS(nav=NS(active=False))}))
    assert not ClientView.wants_live.fget(tab("register", True, {"register": NS(picker=NS(active=True))}))


def test_the_live_image_is_encoded_at_about_the_width_it_is_shown():
    """The main view's image is encoded at the width the stylesheet shows it at (from the canvas
    size the page reports: the canvas's width, or its height times the aspect), never below a
    compact page's, and the stylesheet keeps the image between the docked panels."""
    from monotracker.ui.live_panel import BOTTOM_PX, GAP_PX, TOP_PX, live_css, shown_width

    assert shown_width(None, 16 / 9, 546) == 546
    assert shown_width((1090, 1080), 16 / 9, 546) == 1090 - 2 * GAP_PX  # the width limits
    assert shown_width((1730, 900), 16 / 9, 546) == int((900 - TOP_PX - BOTTOM_PX) * 16 / 9)  # the height limits
    assert shown_width((300, 700), 16 / 9, 546) == 546
    css = live_css(330, 400, 16 / 9)
    assert "left: 336px" in css and "calc(100vw - 742px)" in css and "1.7778" in css
