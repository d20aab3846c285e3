"""Step 1 of one tab: open the CT (file, DICOM folder or the sample), check each detected
fiducial (confirm / reject / undo, add one typed in LPS mm or picked on the head), lock the set.
Slices (axial, coronal, sagittal, LPS-aligned) through the selected fiducial."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from monotracker.ui import status as st
from monotracker.ui.slice_panel import SlicePanel

FID_RGB = {"confirmed": (60, 200, 60), "added": (60, 200, 60), "detected": (240, 200, 0), "rejected": (220, 40, 40)}
CLICK_MODES_CT = ("nothing", "add fiducial")
#: the CT step's "Ball finish" choices -> what the plan states (None: the launch setting)
FINISH_CHOICES = {"as launched": None, "read from each frame": "read", "matte": "matte", "glossy": "glossy"}


def finish_choices(launched: str) -> dict:
    """:data:`FINISH_CHOICES` with the launch setting named in its choice ("as launched
    (read)"): the dropdown says what the plan leaves to the server."""
    return {(f"as launched ({launched})" if v is None else k): v for k, v in FINISH_CHOICES.items()}


def finish_label(finish: str | None, choices: dict = FINISH_CHOICES) -> str:
    """The choice of ``choices`` showing the plan's ``finish`` (None: the launch setting)."""
    return next(k for k, v in choices.items() if v == finish)


class CtStep:
    def __init__(self, view):
        self.view = view
        gui, session = view.gui, view.session
        self.folder = gui.add_folder("Step 1: CT and fiducials")
        with self.folder:
            gui.add_markdown("Open the patient CT (a file or a DICOM folder), or the bundled sample. "
                             "Check each fiducial, then lock the set: nothing else can start before.")
            # after a restart the restored plan has no CT in memory: reload it in one click
            self.b_reload = gui.add_button("Reload the plan's CT", color="blue", visible=False)
            self.h_ct_path = gui.add_text("CT file or folder", "", hint="path on the server: .nii.gz, .nrrd, .mha or a DICOM folder")
            b_open = gui.add_button("Open CT")
            b_sample = gui.add_button("Load sample CT")
            # a DICOM folder with several series: the operator chooses, never a silent pick
            self.h_series_info = gui.add_html("", visible=False)
            self.h_series = gui.add_dropdown("Series", ("-",), initial_value="-", visible=False)
            b_series = gui.add_button("Open chosen series", visible=False)
            self.series_widgets = (self.h_series_info, self.h_series, b_series)
            self.series_choices: dict = {}
            self.series_path = ""
            self.h_progress = gui.add_progress_bar(0.0, visible=False, animated=True)
            self.h_job = gui.add_markdown("")
            self.b_cancel = gui.add_button("Cancel CT job", visible=False)
            self.h_kit_r = gui.add_number("Ball radius (mm)", 4.0, min=0.5, max=20.0, step=0.1,
                                          hint="nominal radius of the kit's balls")
            self.h_kit_hu = gui.add_text("Ball density (HU)", "", hint="blank = unknown; e.g. 1500-2000 ceramic, 3071 steel")
            b_kit = gui.add_button("Apply fiducial kit (detect again)")
            snap0 = session.snapshot()
            self._finish_seen = snap0.ball_finish  # what the dropdown last showed of the plan
            self.finish_choices = finish_choices(snap0.ball_finish_default)
            self.h_finish = gui.add_dropdown(
                "Ball finish", tuple(self.finish_choices), initial_value=finish_label(self._finish_seen, self.finish_choices),
                hint="glossy balls beside their contact shadows need more balls in view before a pose is "
                     "trusted; 'read from each frame' judges the highlight; 'as launched' is the server's "
                     "--ball-finish. Kept in the plan; a running camera restarts with it")
            kit = session.plan_copy().fiducial_kit  # the plan's kit, when it has one
            if kit is not None and kit.radius_mm is not None:
                self.h_kit_r.value = float(kit.radius_mm)
                self.h_kit_hu.value = "" if kit.density_hu is None else f"{kit.density_hu:g}"
            self.h_rejected = gui.add_html("")
            self.h_fid_table = gui.add_html("")
            self.h_fid_sel = gui.add_number("Fiducial number", 0, min=0, max=99, step=1)
            grp = gui.add_button_group("Selected fiducial", ["Confirm", "Reject", "Undo"])
            role = gui.add_button_group("Role of the selected fiducial", ["Registration", "Validation"])
            b_all = gui.add_button("Confirm all detected")
            self.h_new_fid = gui.add_vector3("New fiducial (LPS mm)", (0.0, 0.0, 0.0), step=0.1)
            b_add = gui.add_button("Add fiducial here")
            self.h_click = gui.add_dropdown("Click on head", CLICK_MODES_CT, initial_value="nothing",
                                            hint="what a click on the 3D head surface does")
            b_lock = gui.add_button("Lock fiducials and go to Plan", color="green")
            b_unlock = gui.add_button("Unlock fiducials (edit)")
            gui.add_markdown("**Slices** through the selected fiducial (green confirmed, yellow to check, red rejected)")
            self.slices = SlicePanel(view, "ct")

        @b_open.on_click
        @view.safe("Open CT")
        def _(_event) -> None:
            path = self.h_ct_path.value.strip()
            if not path:
                view.say(False, "Open CT: type the path of a CT file or folder first")
                return
            what, infos = open_ct_choice(path)
            if what == "error":
                self._show_series("", [])
                view.say(False, f"Open CT: {infos}")
                return
            if what == "choose":
                self._show_series(path, infos)
                view.say(False, f"Open CT: this folder holds {len(infos)} series; choose one under Series, then Open chosen series")
                return
            self._show_series("", [])
            r = view.run("Open CT", session.load_ct, path)
            if r is not None and r.ok:
                view.watch_job()

        @self.b_cancel.on_click
        @view.safe("Cancel CT job")
        def _(_event) -> None:
            view.run("Cancel CT job", session.cancel_ct_job)

        @b_series.on_click
        @view.safe("Open chosen series")
        def _(_event) -> None:
            uid = self.series_choices.get(self.h_series.value)
            if not self.series_path or uid is None:
                view.say(False, "Open chosen series: press Open CT on a DICOM folder first")
                return
            r = view.run("Open chosen series", session.load_ct, self.series_path, uid)
            if r is not None and r.ok:
                view.watch_job()

        @b_kit.on_click
        @view.safe("Fiducial kit")
        def _(_event) -> None:
            kit = parse_kit(self.h_kit_r.value, self.h_kit_hu.value)
            if isinstance(kit, str):
                view.say(False, f"Fiducial kit: {kit}")
                return
            r = view.run("Fiducial kit", session.set_fiducial_kit, *kit)
            if r is not None and r.ok and "detecting" in r.message:
                view.watch_job()

        @self.h_finish.on_update
        @view.safe("Ball finish")
        def _(_event) -> None:
            finish = self.finish_choices.get(self.h_finish.value)
            now = session.snapshot().ball_finish
            if finish == now:
                return  # the plan already says so (also: the dropdown set from the plan)
            r = view.run("Ball finish", session.set_ball_finish, finish)
            if r is None or not r.ok:
                self.h_finish.value = finish_label(now, self.finish_choices)  # show what the plan still says

        @self.b_reload.on_click
        @view.safe("Reload CT")
        def _(_event) -> None:
            path = session.snapshot().plan_ct_path
            if not path:
                view.say(False, "Reload CT: the plan names no CT")
                return
            r = view.run("Reload CT", session.load_ct, path)
            if r is not None and r.ok:
                view.watch_job()

        @b_sample.on_click
        @view.safe("Load sample CT")
        def _(_event) -> None:
            r = view.run("Load sample CT", session.load_sample_ct)
            if r is not None and r.ok:
                view.watch_job()

        @self.h_fid_sel.on_update
        def _(_event) -> None:
            with view.lock:
                view.selected_fid = int(self.h_fid_sel.value)

        @grp.on_click
        @view.safe("Fiducial")
        def _(event) -> None:
            word = {"Confirm": "confirmed", "Reject": "rejected", "Undo": "detected"}[event.target.value]
            i = int(self.h_fid_sel.value)
            view.run(f"Fiducial {i}", session.set_fiducial_status, i, word)

        @role.on_click
        @view.safe("Fiducial role")
        def _(event) -> None:
            i = int(self.h_fid_sel.value)
            view.run(f"Fiducial {i} role", session.set_fiducial_role, i, event.target.value.lower())

        @b_all.on_click
        @view.safe("Confirm all detected")
        def _(_event) -> None:
            self._confirm_all()

        @b_add.on_click
        @view.safe("Add fiducial")
        def _(_event) -> None:
            view.run("Add fiducial", session.add_fiducial, np.array(self.h_new_fid.value, float))

        @b_lock.on_click
        @view.safe("Lock fiducials")
        def _(_event) -> None:
            r = view.run("Lock fiducials", session.confirm_fiducials)
            if r is not None and r.ok:
                view.goto("plan")

        @b_unlock.on_click
        @view.safe("Unlock fiducials")
        def _(_event) -> None:
            view.run("Unlock fiducials", session.unlock_fiducials)

    def _show_series(self, path: str, infos: list) -> None:
        """Offer the series of ``path`` to choose from (none: hide the chooser)."""
        self.series_path = path
        self.series_choices = {series_label(i, k): i.uid for k, i in enumerate(infos)}
        if self.series_choices:
            labels = tuple(self.series_choices)
            self.h_series.options = labels
            self.h_series.value = labels[0]
            self.h_series_info.content = series_table(infos)
        for h in self.series_widgets:
            h.visible = bool(self.series_choices)

    def _confirm_all(self) -> None:
        view = self.view
        ids = [f.id for f in view.session.snapshot().fiducials if f.status == "detected"]
        if not ids:
            view.say(False, "Confirm all detected: no detected fiducial waits for a decision")
            return
        for i in ids:
            r = view.session.set_fiducial_status(i, "confirmed")
            if not r.ok:
                view.say(False, f"Fiducial {i}: {r.message}")
                return
        view.say(True, f"Confirmed fiducials {', '.join(map(str, ids))}")

    def render(self, snap) -> None:
        job = snap.job
        self.b_cancel.visible = job is not None and not job.done
        offer = needs_ct_reload(snap)
        if self.b_reload.visible != offer:
            self.b_reload.visible = offer
        if job is not None and not job.done:
            self.h_progress.visible = True
            self.h_progress.value = 100.0 * job.progress
            self.h_job.content = f"**{job.message}** ({100 * job.progress:.0f} %)"
        else:
            self.h_progress.visible = False
            if job is not None and job.error:
                self.h_job.content = f"<div class='mt-msg err'>&#10007; CT: {st._esc(job.error)}</div>"
            elif snap.ct is not None:
                sp = snap.ct.spacing_mm
                notes = "".join(f"<br>note: {st._esc(n)}" for n in snap.ct.notes)
                self.h_job.content = (f"CT **{Path(snap.ct.path).name}**: {snap.ct.shape[2]}x{snap.ct.shape[1]}x"
                                      f"{snap.ct.shape[0]} voxels, {sp[0]:.2f} x {sp[1]:.2f} x {sp[2]:.2f} mm{notes}")
            else:
                self.h_job.content = "No CT loaded."
        self.h_fid_table.content = fiducial_table(snap)
        self.h_rejected.content = rejected_table(snap)
        if snap.ball_finish != self._finish_seen:  # changed elsewhere (another tab, a restored plan)
            self._finish_seen = snap.ball_finish
            self.h_finish.value = finish_label(snap.ball_finish, self.finish_choices)
        with self.view.lock:
            fid_id = self.view.selected_fid
        fid = next((f for f in snap.fiducials if f.id == fid_id), None)
        self.slices.render(snap, None if fid is None else np.asarray(fid.centre_lps_mm))


def fiducial_table(snap) -> str:
    """The fiducial table (status, centre LPS mm, radius mm, score) as HTML."""
    if not snap.fiducials:
        return ""
    lock = ("<b style='color:#1f8f3a'>LOCKED</b>" if snap.fiducials_locked else
            "<b style='color:#b7791f'>not locked: confirm or reject each, then lock</b>")
    rows = []
    for f in snap.fiducials:
        col = "#%02x%02x%02x" % FID_RGB.get(f.status, (0, 0, 0))
        c = f.centre_lps_mm
        role = "" if f.role == "registration" else " <i>(validation: not in the fit)</i>"
        rows.append(f"<tr><td><b>{f.id}</b></td><td style='color:{col}'><b>{st._esc(f.status)}</b>{role}</td>"
                    f"<td>{c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}</td><td>{f.radius_mm:.1f}</td><td>{f.score:.2f}</td></tr>")
    n_ok = sum(f.status in ("confirmed", "added") for f in snap.fiducials)
    return (f"<div class='mt-row'>{len(snap.fiducials)} fiducials, {n_ok} confirmed; {lock}</div>"
            "<table class='mt' id='mt-fiducials'><tr><th>#</th><th>status</th><th>centre LPS mm</th><th>r mm</th>"
            f"<th>score</th></tr>{''.join(rows)}</table>")


def open_ct_choice(path: str) -> tuple[str, object]:
    """What Open CT does with ``path``: ``("load", None)`` (a file, or a folder with one series),
    ``("choose", [SeriesInfo, ...])`` (a DICOM folder with several: the operator chooses), or
    ``("error", one line)``."""
    p = Path(path).expanduser()
    if not p.is_dir():
        return "load", None
    try:
        from monotracker.ct import list_series

        infos = list_series(p)
    except Exception as exc:  # noqa: BLE001 - unreadable folder: one line, the load would say the same
        return "error", str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return ("choose", infos) if len(infos) > 1 else ("load", None)


def series_label(info, k: int) -> str:
    """One dropdown line per series (unique: numbered)."""
    sp = info.spacing_mm
    tilt = f", tilt {info.tilt_deg:.1f} deg" if np.isfinite(info.tilt_deg) and info.tilt_deg >= 0.05 else ""
    bad = "" if info.ok else " (cannot be loaded)"
    return (f"{k + 1}: {info.description or 'no description'}, {info.slices} slices, "
            f"{sp[0]:.2f} x {sp[1]:.2f} x {sp[2]:.2f} mm{tilt}{bad}")


def series_table(infos) -> str:
    """The series of a folder as HTML: description, slices, spacing (mm), tilt, notes."""
    rows = []
    for k, i in enumerate(infos):
        sp = i.spacing_mm
        tilt = f"{i.tilt_deg:.1f}" if np.isfinite(i.tilt_deg) else "-"
        notes = "; ".join(i.notes)
        style = "" if i.ok else " style='color:#c0392b'"
        rows.append(f"<tr><td>{k + 1}</td><td>{st._esc(i.description or '-')}</td><td>{i.slices}</td>"
                    f"<td>{sp[0]:.2f} x {sp[1]:.2f} x {sp[2]:.2f}</td><td>{tilt}</td>"
                    f"<td{style}>{st._esc(notes)}</td></tr>")
    return ("<table class='mt' id='mt-series'><tr><th>#</th><th>description</th><th>slices</th><th>spacing mm</th>"
            f"<th>tilt deg</th><th>notes</th></tr>{''.join(rows)}</table>")


def parse_kit(radius, density_text) -> tuple | str:
    """The kit fields of the CT step: ``(radius_mm, density_hu or None)``, or a one-line reason
    (the session checks the ranges)."""
    text = str(density_text or "").strip()
    if not text:
        return float(radius), None
    try:
        return float(radius), float(text)
    except ValueError:
        return f"density must be a number of HU or blank (unknown), not {text!r}"


def rejected_table(snap) -> str:
    """The dense blobs the detection did not take (centre LPS mm, radius mm, voxels, reason)."""
    ct = snap.ct
    if ct is None or not ct.rejected:
        return ""
    rows = "".join(f"<tr><td>{b.centre_lps_mm[0]:.1f}, {b.centre_lps_mm[1]:.1f}, {b.centre_lps_mm[2]:.1f}</td>"
                   f"<td>{b.radius_mm:.1f}</td><td>{b.n_voxels}</td><td>{st._esc(b.reason)}</td></tr>" for b in ct.rejected)
    return (f"<div class='mt-row'>{len(ct.rejected)} dense blobs not taken as fiducials</div>"
            "<table class='mt' id='mt-rejected'><tr><th>centre LPS mm</th><th>r mm</th><th>voxels</th><th>reason</th></tr>"
            f"{rows}</table>")


def needs_ct_reload(snap) -> bool:
    """A restored plan names a CT that is not loaded (and no CT job runs): offer to reload it."""
    running = snap.job is not None and not snap.job.done
    return snap.ct is None and bool(snap.plan_ct_path) and not running
