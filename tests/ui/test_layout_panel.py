"""The layout planner's page parts (issue 31), view level: the Plan step's text and controls, the
3D drawing of the error map, the numbered suggested balls and the planned camera, and the Register
step's "camera is N mm / N deg from the planned placement" line. The scene and the gui are
recording doubles; the layout is made by hand (its numbers are the truth the page must show)."""

from __future__ import annotations

from types import SimpleNamespace
from unittest.mock import MagicMock

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from monotracker.engine.snapshot import Job, LayoutError, LayoutExpectation, LayoutSummary, frozen_array
from monotracker.ui.layout_panel import MM, LayoutPanel, error_colours, layout_html, placement_line

K = np.array([[1100.0, 0, 640], [0, 1100.0, 360], [0, 0, 1]])


def _planned_pose():
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [100, 10, -20], degrees=True).as_matrix()
    T[:3, 3] = [20.0, -400.0, 150.0]
    return T


def _layout(balls_needed=None, stale=False, done=True, worst_trusted=0.99):
    balls = frozen_array([[10.0, -80.0, 60.0], [-30.0, -85.0, 40.0], [40.0, -70.0, 20.0], [0.0, -60.0, 90.0],
                          [-50.0, -60.0, 70.0], [30.0, -40.0, 100.0]])
    sug = LayoutExpectation(6, 6, LayoutError(6, 0.21, 0.43, 0.24, 1.0), LayoutError(5, 0.30, 0.61, 0.34, worst_trusted),
                            2, "")
    cur = LayoutExpectation(9, 8, LayoutError(8, 0.36, 0.77, 0.42, 0.99), LayoutError(7, 0.43, 0.86, 0.49, 0.98), 4, "")
    return LayoutSummary(job=Job("plan_layout", 1.0 if done else 0.4, "layout planned" if done else "camera pose 3 of 8",
                                 None, done),
                         balls_lps_mm=balls, from_fiducial=(3, -1, -1, -1, -1, -1), T_ct_cam=frozen_array(_planned_pose()),
                         camera_distance_mm=420.0, K=frozen_array(K), image_size=(1280, 720), suggestion=sug,
                         current=cur, current_best=None, balls_needed=balls_needed,
                         notes=("6 balls reach 95 % trusted frames with one hidden",) if balls_needed else (),
                         candidates_lps_mm=frozen_array(np.arange(30.0).reshape(10, 3)),
                         error_map_mm=frozen_array([0.3, 0.45, 0.6, 0.9, np.nan, 0.3, 0.32, 2.0, 0.5, 0.4]),
                         target_lps_mm=frozen_array([-18.0, -20.0, 46.0]), noise_px=0.2, radius_mm=4.0, stale=stale)


def test_error_colours_run_green_to_red_and_grey_where_unusable():
    e = np.array([0.30, 0.31, 0.32, 0.33, 0.34, 0.35, 0.36, 0.37, 0.38, 0.39, 0.40, 2.0, np.nan])
    cols, lo, hi = error_colours(e)
    assert lo == 0.30 and hi == pytest.approx(np.quantile(e[:12], 0.9))  # the largest tenth is red
    assert cols[0, 1] > 200 and cols[0, 0] < 30              # the smallest: green
    mid = int(np.argmin(np.abs(e[:12] - (lo + hi) / 2)))
    assert cols[mid, 0] > 150 and cols[mid, 1] > 150          # halfway: yellow
    assert cols[11, 0] > 200 and cols[11, 1] < 30            # the top: red
    assert (cols[12] == 150).all()                           # NaN: grey
    flat, lo, hi = error_colours(np.full(5, 0.2))             # a flat map: all green, not a division by 0
    assert hi > lo and (flat[:, 1] > 200).all()


def test_plan_step_text_shows_what_to_expect():
    html = layout_html(_layout())
    assert "6 balls, camera 420 mm from the head" in html and "99 % trusted frames with the worst ball hidden" in html
    # the suggestion's and the plan's fiducials' figures (mean, 95 %, trusted)
    assert "<td>0.21</td><td>0.43</td><td>100 %</td>" in html and "<td>0.30</td><td>0.61</td><td>99 %</td>" in html
    assert "<td>0.36</td><td>0.77</td><td>99 %</td>" in html and "worst ball hidden (#3)" in html
    # each suggested position, numbered from 1, the kept fiducial named
    assert "<td><b>1</b></td><td>10.0, -80.0, 60.0</td><td>fiducial #3 stays</td>" in html
    assert "<td><b>6</b></td><td>30.0, -40.0, 100.0</td><td>new</td>" in html
    lo, hi = error_colours(np.asarray(_layout().error_map_mm))[1:]
    assert f"green {lo:.2f} mm" in html and f"red {hi:.2f} mm" in html
    needed = layout_html(_layout(balls_needed=8, worst_trusted=0.9))
    assert "8 balls needed</b> for 95 % trusted frames with one hidden" in needed
    assert "plan again" in layout_html(_layout(stale=True))
    assert "camera pose 3 of 8 (40 %)" in layout_html(_layout(done=False))
    # with the detector's losses: the verdict says it, amber under the trusted share asked for
    import dataclasses
    lay = _layout()
    lossy = dataclasses.replace(lay, suggestion=dataclasses.replace(lay.suggestion, found_probability=0.6,
                                                                     trusted_with_losses=0.41, pose_with_losses=0.83))
    html = layout_html(lossy)
    assert "color:#b7791f'>41 % with the detector's losses</b> (each ball found at 60 %)" in html
    assert "each ball found at 60 % (the detector's losses)</td><td colspan='2'>a pose in 83 % of setups</td>" \
        "<td>41 %</td>" in html
    assert "with the detector's losses" not in layout_html(lay)
    # balls short of skin around them: the outlook says how many and at what share
    short = dataclasses.replace(lossy, current=dataclasses.replace(
        lay.current, found_probability=0.6, found_short=0.27, short_of_skin=2, trusted_with_losses=0.18,
        pose_with_losses=0.5))
    assert ("each ball found at 60 % (2 on the head&#x27;s outline or beside the drape at 27 %) (the detector's "
            "losses)</td><td colspan='2'>a pose in 50 % of setups</td><td>18 %</td>") in layout_html(short)
    failed = layout_html(LayoutSummary(job=Job("plan_layout", 1.0, "layout not planned", "set the target first", True)))
    assert "layout not planned:</b> set the target first" in failed


def _pose_snap(T_cam_ct, trusted=True, layout=None):
    return SimpleNamespace(layout=layout or _layout(),
                           pose=SimpleNamespace(trusted=trusted, T_cam_ct=T_cam_ct, predicted_tre_mm=0.512))


def test_register_line_says_how_far_the_camera_is_from_the_plan():
    T = _planned_pose()
    moved = T.copy()
    moved[:3, 3] += 37.0 * T[:3, 0]  # 37 mm sideways, same direction
    moved[:3, :3] = T[:3, :3] @ Rotation.from_euler("y", 12, degrees=True).as_matrix()  # 12 deg turned
    line = placement_line(_pose_snap(np.linalg.inv(moved)))
    assert "<b>37 mm / 12&deg;</b> from the planned placement" in line
    assert "predicted error at the target <b>0.51 mm</b> (planned 0.42 mm)" in line
    assert placement_line(_pose_snap(np.linalg.inv(moved), trusted=False)) == ""
    assert placement_line(_pose_snap(None)) == ""
    assert placement_line(SimpleNamespace(layout=None, pose=_pose_snap(T).pose)) == ""


def _scene():
    scene = MagicMock()
    return scene


def test_scene_draws_the_map_the_numbered_balls_and_the_planned_camera_once():
    panel = LayoutPanel.__new__(LayoutPanel)
    panel.h_show = SimpleNamespace(value=True)
    lay = _layout()
    snap = SimpleNamespace(layout=lay)
    scene, keys = _scene(), {}
    panel.render_scene(scene, keys, snap)
    (name, pts, cols), kw = scene.add_point_cloud.call_args
    assert name == "/ct/layout/map" and np.allclose(pts, np.asarray(lay.candidates_lps_mm) * MM)
    assert (cols == error_colours(lay.error_map_mm)[0]).all()
    labels = {c.args[0]: c.args[1] for c in scene.add_label.call_args_list}
    assert [labels[f"/ct/layout/l{i}"] for i in range(1, 7)] == [f"S{i}" for i in range(1, 7)]
    spheres = {c.args[0]: c.kwargs["position"] for c in scene.add_icosphere.call_args_list}
    assert np.allclose(spheres["/ct/layout/b6"], np.asarray(lay.balls_lps_mm[5]) * MM)
    fr = scene.add_camera_frustum.call_args
    T = _planned_pose()
    assert np.allclose(fr.kwargs["position"], T[:3, 3] * MM)
    w, x, y, z = fr.kwargs["wxyz"]
    assert np.allclose(Rotation.from_quat([x, y, z, w]).as_matrix(), T[:3, :3], atol=1e-9)
    assert fr.kwargs["fov"] == pytest.approx(2 * np.arctan(360 / 1100.0))
    # the same layout again: nothing is sent; the scene reset (keys cleared): drawn again
    scene2 = _scene()
    panel.render_scene(scene2, keys, SimpleNamespace(layout=lay))
    assert not scene2.method_calls
    keys.clear()
    panel.render_scene(scene2, keys, SimpleNamespace(layout=lay))
    assert scene2.add_point_cloud.called
    # hidden by the checkbox: removed once, then nothing
    panel.h_show = SimpleNamespace(value=False)
    scene3 = _scene()
    panel.render_scene(scene3, keys, snap)
    panel.render_scene(scene3, keys, snap)
    scene3.remove_by_name.assert_called_once_with("/ct/layout")
    assert not scene3.add_point_cloud.called


def test_plan_button_asks_the_engine_with_the_chosen_count():
    clicks = []
    gui = MagicMock()
    gui.add_button_group.return_value.on_click.side_effect = lambda fn: clicks.append(fn) or fn
    gui.add_number.return_value = SimpleNamespace(value=7)
    gui.add_checkbox.return_value = SimpleNamespace(value=False)
    ran = []
    view = SimpleNamespace(gui=gui, session=SimpleNamespace(plan_layout="PLAN", cancel_layout="CANCEL"),
                           safe=lambda what: (lambda fn: fn), run=lambda *a: ran.append(a))
    panel = LayoutPanel(view)
    clicks[0](SimpleNamespace(target=SimpleNamespace(value="Plan layout")))
    clicks[0](SimpleNamespace(target=SimpleNamespace(value="Cancel")))
    assert ran == [("Plan layout", "PLAN", 7, False), ("Cancel layout", "CANCEL")]
    # progress shows while the job runs, and goes when it ends
    panel.h_progress = SimpleNamespace(visible=False, value=0.0)
    panel.h_info = SimpleNamespace(content="")
    panel.render(SimpleNamespace(layout=_layout(done=False)))
    assert panel.h_progress.visible and panel.h_progress.value == 40.0
    panel.render(SimpleNamespace(layout=_layout()))
    assert not panel.h_progress.visible and "mt-layout-table" in panel.h_info.content
