"""Step 2 of one tab: the entry on the skin and the target inside, by a click on the head or
typed in LPS mm (or the sample plan); the engine's metrics and refusals; the Slicer export,
downloaded by the browser; "New plan" starts over (the engine clears CT, fiducials and path)."""

from __future__ import annotations

import io
import zipfile

import numpy as np

from monotracker.engine.plan import distance_segment_to_points_mm
from monotracker.ui.layout_panel import LayoutPanel
from monotracker.ui.navigation_panel import NavigationPanel
from monotracker.ui.slice_panel import SlicePanel
from monotracker.ui.status import fmt

CLICK_MODES_PLAN = ("set entry", "set target", "nothing")


class PlanStep:
    def __init__(self, view):
        self.view = view
        gui, session = view.gui, view.session
        self.folder = gui.add_folder("Step 2: plan the path")
        with self.folder:
            gui.add_markdown("Pick the **entry** on the skin and the **target** inside: click the head "
                             "(choose what the click sets below) or type LPS coordinates in mm.")
            self.h_click = gui.add_dropdown("Head click sets", CLICK_MODES_PLAN, initial_value="set entry",
                                            hint="what a click on the 3D head surface does")
            self.h_entry = gui.add_vector3("Entry (LPS mm)", (0.0, 0.0, 0.0), step=0.1)
            b_e = gui.add_button("Set entry")
            self.h_target = gui.add_vector3("Target (LPS mm)", (0.0, 0.0, 0.0), step=0.1)
            b_t = gui.add_button("Set target")
            b_s = gui.add_button("Use the sample plan")
            b_new = gui.add_button("New plan (start over: clear CT, fiducials, path)")
            self.h_info = gui.add_html("")
            self.b_next = b_next = gui.add_button(PLAN_GATE[False], color="gray")
            b_x = gui.add_button("Export to 3D Slicer (.mrk.json)")
            self.layout = LayoutPanel(view)  # where the balls and the camera go (ui/layout_panel.py)
            gui.add_markdown("**Navigation view** in the main view: slices through the target (or a picked "
                             "point), probe's eye and along-path; a click on a slice can set the entry, "
                             "the target or add a fiducial")
            self.nav = NavigationPanel(view, "plan", live=False)
            gui.add_markdown("**Slices** through the target (path: cyan entry, magenta target)")
            self.slices = SlicePanel(view, "plan")
        self._synced: dict = {}

        @b_e.on_click
        @view.safe("Set entry")
        def _(_event) -> None:
            self._set_point("entry", session.set_entry)

        @b_t.on_click
        @view.safe("Set target")
        def _(_event) -> None:
            self._set_point("target", session.set_target)

        @b_s.on_click
        @view.safe("Sample plan")
        def _(_event) -> None:
            view.run("Sample plan", session.use_sample_plan)

        @b_new.on_click
        @view.safe("New plan")
        def _(_event) -> None:
            self._new_plan()

        @b_next.on_click
        @view.safe("Go to Register")
        def _(_event) -> None:
            if not session.snapshot().plan.complete:
                view.say(False, "Go to Register: set both the entry and the target first")
                return
            view.goto("register")
            view.say(True, "Path planned. Choose the camera and start it.")

        @b_x.on_click
        @view.safe("Export")
        def _(_event) -> None:
            self._export()

    def _set_point(self, key: str, command) -> None:
        """Set the entry or the target from its typed field; a refused value does not stay in the
        field beside the accepted one: the field goes back to the plan's point (or zeros)."""
        handle = self.h_entry if key == "entry" else self.h_target
        r = self.view.run(f"Set {key}", command, np.array(handle.value, float))
        if r is not None and not r.ok:
            p = getattr(self.view.session.snapshot().plan, f"{key}_lps_mm")
            val = (0.0, 0.0, 0.0) if p is None else tuple(round(float(v), 2) for v in p)
            self._synced[key] = val
            handle.value = val

    def _new_plan(self) -> None:
        """Start over: the engine forgets CT, fiducials and path (refused while armed)."""
        view = self.view
        r = view.run("New plan", view.session.new_plan)
        if r is not None and r.ok:
            view.goto("ct")

    def _export(self) -> None:
        """The engine writes the markups to ``<home>/slicer/``; the browser gets them as a download
        (one file as is, several in a zip)."""
        view = self.view
        folder = view.session.home / "slicer"
        try:
            files = view.session.export_slicer_markups(folder)
        except Exception as exc:  # noqa: BLE001 - InputError or I/O: one line for the operator
            view.say(False, f"Export: {exc}")
            return
        if hasattr(files, "ok"):  # refused (this station is not in control)
            view.say(False, f"Export: {files.message}")
            return
        files = list(files)
        if not files:
            view.say(False, "Export: nothing was written")
            return
        if len(files) == 1:
            name, data = files[0].name, files[0].read_bytes()
        else:
            buf = io.BytesIO()
            with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
                for p in files:
                    z.write(p, arcname=p.name)
            name, data = "monotracker_slicer_markups.zip", buf.getvalue()
        view.client.send_file_download(name, data, save_immediately=True)
        view.say(True, f"Exported {', '.join(p.name for p in files)} (downloaded as {name}; also in {folder})")

    def render(self, snap) -> None:
        self.h_info.content = plan_info(snap)
        self.layout.render(snap)
        gate(self.b_next, snap.plan.complete, PLAN_GATE)
        # show the plan's points in the typed fields whenever the plan changes (not while typing)
        for key, handle, p in (("entry", self.h_entry, snap.plan.entry_lps_mm),
                               ("target", self.h_target, snap.plan.target_lps_mm)):
            val = None if p is None else tuple(round(float(v), 2) for v in p)
            if val is not None and self._synced.get(key) != val:
                self._synced[key] = val
                handle.value = val
        t = snap.plan.target_lps_mm
        self.slices.render(snap, None if t is None else np.asarray(t))


#: the Plan step's "go on" button: green only once the path exists, else what is missing
PLAN_GATE = {True: "Path is good: go to Register", False: "Go to Register: set the entry and the target first"}
#: a target this close under the entry (mm) is in or near the skull: the plan says so
SHALLOW_TARGET_MM = 10.0


def gate(button, ok: bool, labels: dict) -> None:
    """A step's "go on" ``button``: green with ``labels[True]`` when its precondition holds,
    grey with ``labels[False]`` (what is missing) otherwise; only changed props are sent."""
    label, colour = labels[bool(ok)], ("green" if ok else "gray")
    if button.label != label:
        button.label = label
    if button.color != colour:
        button.color = colour


def plan_info(snap) -> str:
    """Entry, target, length, angle to the skin normal, distance path to each fiducial (HTML)."""
    p = snap.plan
    e, t = p.entry_lps_mm, p.target_lps_mm
    lines = [f"<div class='mt-row'>Entry: <b>{'-' if e is None else ', '.join(f'{v:.1f}' for v in e)}</b> mm LPS</div>",
             f"<div class='mt-row'>Target: <b>{'-' if t is None else ', '.join(f'{v:.1f}' for v in t)}</b> mm LPS</div>"]
    if p.complete:
        lines.append(f"<div class='mt-row' id='mt-plan-metrics'>Length <b>{fmt(p.path_length_mm, ' mm')}</b>, "
                     f"angle to skin normal <b>{fmt(p.angle_to_skin_normal_deg, '&deg;')}</b>, "
                     f"closest fiducial <b>{fmt(p.distance_to_fiducials_mm, ' mm')}</b></div>")
        cells = []
        for f in snap.fiducials:
            if f.status in ("confirmed", "added"):
                d = distance_segment_to_points_mm(e, t, np.asarray(f.centre_lps_mm)[None, :])
                cells.append(f"<td>#{f.id}: {float(np.min(d)):.1f}</td>")
        lines.append(f"<div class='mt-row'>Distance path to each fiducial (mm):</div><table class='mt'><tr>{''.join(cells)}</tr></table>")
        if p.path_length_mm is not None and p.path_length_mm <= SHALLOW_TARGET_MM:
            lines.append(f"<div class='mt-alert' id='mt-shallow' style='background:#b7791f'>WARNING: the target is only "
                         f"{p.path_length_mm:.1f} mm under the entry (&le; {SHALLOW_TARGET_MM:.0f} mm): in or near the "
                         f"skull; check it on the slices</div>")
    return "".join(lines)
