"""The fiducial-layout and camera-placement planner in the page (issue 31).

At the Plan step (:class:`LayoutPanel`, built inside the step's folder): the ball count, a quick
or full search, "Plan layout" / "Cancel", the job's progress, and what to expect (predicted
error at the target, mean / 95 % / trusted share, with every ball seen and with the worst one
hidden, for the suggestion and for the plan's fiducials; "N balls needed" when 95 % trusted is
out of reach). The suggested positions are also drawn on the Plan step's slices and navigation
views (``ui/slices.py``: ``suggested_balls``, ``draw_suggested``). In the 3D view (CT frame,
:meth:`LayoutPanel.render_scene`): the map of the predicted error at the target as coloured
points on the head (one per candidate ball position: the error with the worst ball hidden if one
suggested ball moved there; green = the smallest, red = the largest tenth, see the legend), the
suggested positions as numbered balls, and the planned camera with its field of view and its
line of sight to the head.

At the Register step (:func:`placement_line`): "camera is N mm / N deg from the planned
placement; predicted error X mm" while a layout exists and the pose is trusted.

The planning runs in the engine (``Session.plan_layout``, ``engine/layout_job.py``); this module
only shows ``snap.layout``. Scene units: metres (CT mm x ``MM``).
"""

from __future__ import annotations

import numpy as np

from monotracker.engine.layout_job import placement_offset
from monotracker.ui import status as st
from monotracker.ui.slices import SUGGESTED_BGR
from monotracker.ui.status import fmt

MM = 1e-3  # scene metres per millimetre (as ui/scene.py)
#: colours of the error map: green (the smallest error) -> yellow -> red (this quantile and above)
MAP_TOP_QUANTILE = 0.9
SUGGESTED_RGB = SUGGESTED_BGR[::-1]  # the same blue as on the slices
CAMERA_RGB = SUGGESTED_RGB


def error_colours(err_mm: np.ndarray, top: float = MAP_TOP_QUANTILE) -> tuple[np.ndarray, float, float]:
    """(m, 3) uint8 colours for the error map, and the (low, high) mm the scale runs over: green at
    the smallest finite error, yellow halfway, red at the ``top`` quantile of the finite errors and
    above (moving one ball changes the error by little, so a scale to the largest value would
    paint nearly every point the same); grey for NaN (a position the planned camera cannot use)."""
    e = np.asarray(err_mm, float)
    ok = np.isfinite(e)
    out = np.full((len(e), 3), 150, np.uint8)
    if not ok.any():
        return out, float("nan"), float("nan")
    lo = float(e[ok].min())
    hi = float(np.quantile(e[ok], top))
    if hi <= lo:
        hi = lo + max(0.05 * lo, 1e-6)
    u = np.clip((e[ok] - lo) / (hi - lo), 0.0, 1.0)
    r = np.clip(2.0 * u, 0.0, 1.0)
    g = np.clip(2.0 * (1.0 - u), 0.0, 1.0)
    out[ok] = (np.stack([r, g, np.zeros_like(u)], axis=1) * 220 + 20).astype(np.uint8)
    return out, lo, hi


def _err_cells(e) -> str:
    if e is None:
        return "<td colspan='3'>no pose</td>"
    return f"<td>{e.mean_mm:.2f}</td><td>{e.p95_mm:.2f}</td><td>{100 * e.trusted:.0f} %</td>"


def _rows(label: str, x) -> str:
    if x is None:
        return ""
    out = (f"<tr><td>{st._esc(label)} ({x.balls_seen} of {x.balls} seen)</td>{_err_cells(x.all_seen)}</tr>"
           f"<tr><td>&nbsp;&nbsp;worst ball hidden"
           + ("" if x.worst_ball is None else f" (#{x.worst_ball + 1})") + f"</td>{_err_cells(x.worst_hidden)}</tr>")
    if x.trusted_with_losses is not None:
        out += (f"<tr><td>&nbsp;&nbsp;{st._esc(x.found_text)} (the detector's losses)"
                f"</td><td colspan='2'>a pose in {100 * x.pose_with_losses:.0f} % of setups</td>"
                f"<td>{100 * x.trusted_with_losses:.0f} %</td></tr>")
    if x.all_seen is None or x.worst_hidden is None:
        out += f"<tr><td colspan='4'>{st._esc(x.reason)}</td></tr>"
    return out


def layout_html(lay) -> str:
    """The Plan step's text for ``snap.layout`` (HTML): the job, what to expect, the suggested
    positions, the map's legend, the notes."""
    if lay is None:
        return ("<div class='mt-row' id='mt-layout'>Plan where the balls and the camera go for a small error at "
                "the target (before the patient is in the room).</div>")
    job = lay.job
    parts = []
    if not job.done:
        parts.append(f"<div class='mt-row'>{st._esc(job.message)} ({100 * job.progress:.0f} %)</div>")
    elif job.error:
        parts.append(f"<div class='mt-row' style='color:#c81e1e'><b>{st._esc(job.message)}:</b> "
                     f"{st._esc(job.error)}</div>")
    if lay.ready:
        if lay.stale:
            parts.append("<div class='mt-row' style='color:#b7791f'><b>The CT, the fiducials or the path changed "
                         "since this layout was planned: plan again.</b></div>")
        sug = lay.suggestion
        w = sug.worst_hidden if sug is not None else None
        ok = w is not None and w.trusted >= lay.min_trusted
        head = (f"{len(lay.balls_lps_mm)} balls, camera {fmt(lay.camera_distance_mm, ' mm', 0)} from the head, "
                f"image noise {fmt(lay.noise_px, ' px', 2)}")
        if lay.balls_needed is not None:
            verdict = (f"<b style='color:#c81e1e'>{lay.balls_needed} balls needed</b> for "
                       f"{100 * lay.min_trusted:.0f} % trusted frames with one hidden")
        elif ok:
            verdict = f"<b style='color:#1f8f3a'>{100 * w.trusted:.0f} % trusted frames with the worst ball hidden</b>"
        else:
            verdict = (f"<b style='color:#c81e1e'>under {100 * lay.min_trusted:.0f} % trusted frames with one "
                       "hidden</b>")
        if sug is not None and sug.trusted_with_losses is not None:
            colour = "#1f8f3a" if sug.trusted_with_losses >= lay.min_trusted else "#b7791f"
            verdict += (f"; <b style='color:{colour}'>{100 * sug.trusted_with_losses:.0f} % with the detector's "
                        f"losses</b> ({st._esc(sug.found_text)})")
        parts.append(f"<div class='mt-row'>Suggested layout: {head}; {verdict}</div>")
        parts.append("<table class='mt' id='mt-layout-table'><tr><th>predicted error at the target</th><th>mean "
                     "mm</th><th>95 % mm</th><th>trusted</th></tr>" + _rows("suggestion, planned camera", sug)
                     + _rows("plan's fiducials, planned camera", lay.current)
                     + _rows("plan's fiducials, their best camera", lay.current_best) + "</table>")
        balls = "".join(f"<tr><td><b>{i + 1}</b></td><td>{p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}</td><td>"
                        + (f"fiducial #{fid} stays" if fid >= 0 else "new") + "</td></tr>"
                        for i, (p, fid) in enumerate(zip(lay.balls_lps_mm, lay.from_fiducial)))
        parts.append("<table class='mt' id='mt-layout-balls'><tr><th>ball</th><th>centre LPS mm</th><th></th></tr>"
                     + balls + "</table>")
        _, lo, hi = error_colours(lay.error_map_mm)
        if np.isfinite(lo):
            parts.append(f"<div class='mt-row'>Map on the head: the error at the target (RMS, worst ball hidden) if "
                         f"one ball moved there: <span style='color:#1f8f3a'><b>green {lo:.2f} mm</b></span> to "
                         f"<span style='color:#c81e1e'><b>red {hi:.2f} mm</b></span> and more (the largest tenth); grey: not usable "
                         "from the planned camera. Blue: the suggested balls (numbered) and the planned camera.</div>")
        for n in lay.notes:
            parts.append(f"<div class='mt-row'>note: {st._esc(n)}</div>")
    return f"<div id='mt-layout'>{''.join(parts)}</div>"


def placement_line(snap) -> str:
    """The Register step's live line (HTML): how far the camera is from the planned placement and
    the predicted error at the target now; empty without a layout or a trusted pose."""
    lay, pose = snap.layout, snap.pose
    if lay is None or not lay.ready or pose is None or not pose.trusted or pose.T_cam_ct is None:
        return ""
    mm, deg = placement_offset(lay.T_ct_cam, pose.T_cam_ct)
    planned = lay.current.all_seen if lay.current is not None else None
    extra = "" if planned is None else f" (planned {planned.rms_mm:.2f} mm)"
    stale = " &mdash; the plan changed since the layout was planned" if lay.stale else ""
    return (f"<div class='mt-row' id='mt-placement'>Camera is <b>{mm:.0f} mm / {deg:.0f}&deg;</b> from the planned "
            f"placement; predicted error at the target <b>{fmt(pose.predicted_tre_mm, ' mm', 2)}</b>{extra}{stale}"
            "</div>")


class LayoutPanel:
    """The planner's controls and text inside the Plan step's folder (see the module docstring)."""

    def __init__(self, view):
        self.view = view
        gui, session = view.gui, view.session
        gui.add_markdown("**Ball and camera layout**: where to put the balls and the camera so that the error at "
                         "the target is small, with a margin for one hidden ball")
        self.h_balls = gui.add_number("Balls", 9, min=4, max=16, step=1, hint="how many balls (4-16)")
        self.h_quick = gui.add_checkbox("Quick search", True, hint="8 camera directions, no refinement: seconds "
                                        "instead of tens of seconds")
        grp = gui.add_button_group("Layout", ["Plan layout", "Cancel"])
        self.h_progress = gui.add_progress_bar(0.0, visible=False, animated=True)
        self.h_show = gui.add_checkbox("Show the layout in 3D", True)
        self.h_info = gui.add_html(layout_html(None))

        @grp.on_click
        @view.safe("Layout")
        def _(event) -> None:
            if event.target.value == "Cancel":
                view.run("Cancel layout", session.cancel_layout)
            else:
                view.run("Plan layout", session.plan_layout, int(self.h_balls.value), bool(self.h_quick.value))

    def render(self, snap) -> None:
        lay = snap.layout
        running = lay is not None and not lay.job.done
        self.h_progress.visible = running
        if running:
            self.h_progress.value = round(100.0 * lay.job.progress, 1)
        self.h_info.content = layout_html(lay)

    # ------------------------------------------------------------------ the 3D view (CT frame)
    def render_scene(self, scene, keys, snap) -> None:
        """Draw the layout under ``/ct/layout`` when it (or the checkbox) changed; ``keys`` is the
        tab's scene-key dict (``keys["layout"]`` what is drawn)."""
        lay = snap.layout
        show = bool(self.h_show.value) and lay is not None and lay.ready
        # what is drawn: (shown, the balls array itself, compared by identity, stale)
        key = (True, lay.balls_lps_mm, lay.stale) if show else (False, None, None)
        drawn = keys.get("layout")  # None: nothing drawn since the scene was reset
        if drawn is not None and drawn[0] == key[0] and drawn[1] is key[1] and drawn[2] == key[2]:
            return
        keys["layout"] = key
        try:
            scene.remove_by_name("/ct/layout")
        except Exception:  # noqa: BLE001 - viser raises when the group does not exist yet
            pass
        if not show:
            return
        scene.add_frame("/ct/layout", show_axes=False)
        C = np.asarray(lay.candidates_lps_mm)
        cols, _, _ = error_colours(lay.error_map_mm)
        scene.add_point_cloud("/ct/layout/map", C * MM, cols, point_size=3.0 * MM, point_shape="circle")
        r = float(lay.radius_mm or 4.0)
        for i, p in enumerate(np.asarray(lay.balls_lps_mm)):
            scene.add_icosphere(f"/ct/layout/b{i + 1}", radius=r * MM, color=SUGGESTED_RGB, position=p * MM,
                                cast_shadow=False, receive_shadow=False)
            scene.add_label(f"/ct/layout/l{i + 1}", f"S{i + 1}", position=(p + [0.0, 0.0, 2.0 * r]) * MM)
        self._camera(scene, lay)

    def _camera(self, scene, lay) -> None:
        from monotracker.ui.scene import wxyz

        T = np.asarray(lay.T_ct_cam)
        K, size = lay.K, lay.image_size
        fov = 2 * np.arctan2(size[1] / 2, K[1, 1])
        # the frustum drawn 120 mm deep: the camera's field of view, at the planned place
        scene.add_camera_frustum("/ct/layout/camera", fov=float(fov), aspect=float(size[0] / size[1]), scale=0.12,
                                 thickness=2.0, thickness_units="screen", color=CAMERA_RGB,
                                 wxyz=wxyz(T[:3, :3]), position=T[:3, 3] * MM)
        aim = T[:3, 3] + float(lay.camera_distance_mm) * T[:3, 2]
        scene.add_line_segments("/ct/layout/sight", np.array([[T[:3, 3], aim]]) * MM, CAMERA_RGB, thickness=1.5,
                                thickness_units="screen")
        scene.add_label("/ct/layout/camera_label", f"planned camera ({lay.camera_distance_mm:.0f} mm)",
                        position=T[:3, 3] * MM)
