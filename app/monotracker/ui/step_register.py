"""Step 3 of one tab: camera source and calibration, start/stop; the live image with the
overlay (shared JPEG, see :mod:`monotracker.ui.stream`), the pose banner, the per-fiducial table
with the OCCLUSION alert; learning the ball colour from one click on a ball
(:mod:`monotracker.ui.ball_colour_pick`); simulated faults (sim only)."""

from __future__ import annotations

import time
from pathlib import Path


from monotracker.engine.rigs.sources import SOURCES
from monotracker.ui import status as st
from monotracker.ui.layout_panel import placement_line
from monotracker.ui.freshness import figure_html, pose_figures, pose_why, residuals_live
from monotracker.ui.status import fmt
from monotracker.ui.step_plan import gate

CAMERA_SOURCES = tuple(kind.example for kind in SOURCES.values())  # the engine's table of source kinds
FAULTS_UI = ("none", "occlude-all", "camera-freeze", "bad-pose", "robot-disconnect")


class RegisterStep:
    def __init__(self, view):
        self.view = view
        gui, session = view.gui, view.session
        self.folder = gui.add_folder("Step 3: register (camera)")
        with self.folder:
            src = session.config.camera
            opts = CAMERA_SOURCES if src in CAMERA_SOURCES else (src,) + CAMERA_SOURCES
            self.h_pose_banner = gui.add_html("")
            grp = gui.add_button_group("Camera", ["Start camera", "Stop camera"])
            self.h_cam_src = gui.add_dropdown("Camera source", opts, initial_value=src)
            self.h_cam_path = gui.add_text("Video file / device / folder", "", hint="for file:PATH / folder:PATH / device:N")
            self.h_calib = gui.add_text("Calibration file", "", hint="OpenCV YAML/JSON; empty for the simulated camera")
            b_apply = gui.add_button("Use this camera")
            b_calib = gui.add_button("Calibrate camera / hand-eye")  # ui/step_calibration.py
            pick = gui.add_button_group("Ball colour", ["Learn ball colour (click a ball)", "Cancel"])
            self.h_ball_xy = gui.add_vector2("Ball at x, y (px)", (0.0, 0.0), step=1.0,
                                             hint="pixel of the full-resolution camera frame")
            b_ball_xy = gui.add_button("Learn ball colour at x, y")
            self.h_colour = gui.add_html("")
            self.h_reg_table = gui.add_html("")
            self.h_fault = gui.add_dropdown("Simulate a fault (sim only)", FAULTS_UI, initial_value="none")
            b_f = gui.add_button("Inject fault")
            self.b_next = b_next = gui.add_button(REGISTER_GATE[False], color="gray")

        @b_apply.on_click
        @view.safe("Camera")
        def _(_event) -> None:
            self._apply_camera()

        @grp.on_click
        @view.safe("Camera")
        def _(event) -> None:
            if event.target.value == "Start camera":
                view.run("Start camera", session.start_camera)
            else:
                view.run("Stop camera", session.stop_camera)

        from monotracker.ui.ball_colour_pick import BallColourPicker

        self.picker = BallColourPicker(view, on_result=self._show_colour_result, on_end=lambda: view.show_step())

        @pick.on_click
        @view.safe("Ball colour")
        def _(event) -> None:
            if event.target.value == "Cancel":
                self.picker.cancel()
                self._show_colour_result("")
            else:
                self.picker.start()
            view.show_step()  # the live image steps aside for the pick's frame in the 3D view, and back

        @b_ball_xy.on_click
        @view.safe("Ball colour")
        def _(_event) -> None:
            self.picker.learn_at(*self.h_ball_xy.value)

        @b_f.on_click
        @view.safe("Fault")
        def _(_event) -> None:
            view.run("Fault", session.inject_fault, self.h_fault.value)

        @b_calib.on_click
        @view.safe("Calibrate")
        def _(_event) -> None:
            view.goto("calibration")

        @b_next.on_click
        @view.safe("Go to Robot")
        def _(_event) -> None:
            snap = session.snapshot()
            why = pose_why(snap)
            if why:
                view.say(False, f"Go to Robot: the registration is not good yet: {why}")
                return
            view.goto("robot")
            view.say(True, "Registration good: arm the robot (Arm, PIN), then start tracking")

    def _apply_camera(self) -> None:
        view = self.view
        src = self.h_cam_src.value
        extra = self.h_cam_path.value.strip()
        if src.endswith((":PATH", ":DIR")) or src.startswith("device:"):
            kind = src.split(":", 1)[0]
            if extra:
                src = f"{kind}:{extra}"
            elif src.endswith((":PATH", ":DIR")):
                view.say(False, f"Camera: type the {kind} path in 'Video file / device / folder'")
                return
        calib = self.h_calib.value.strip() or None
        if calib is not None and not Path(calib).exists():
            view.say(False, f"Camera: calibration file not found: {calib}")
            return
        view.run("Camera", view.session.set_camera, src, calib)

    def _show_colour_result(self, text: str) -> None:
        self.h_colour.content = (f"<div class='mt-row' id='mt-ball-colour'>{st._esc(text)}</div>" if text else "")

    def render(self, snap) -> None:
        wall_of = lambda t: self.view.wall_time(snap, t)
        self.h_pose_banner.content = pose_banner(snap, wall_of)
        gate(self.b_next, not pose_why(snap), REGISTER_GATE)
        self.h_reg_table.content = (placement_line(snap) + validation_line(snap.pose)
                                    + registration_table(snap.pose, snap, wall_of)
                                    + recording_line(snap))


#: the Register step's "go on" button: green only with a trusted, fresh pose
REGISTER_GATE = {True: "Registration is good: go to Robot",
                 False: "Go to Robot: needs a valid pose (start the camera, all fiducials in view)"}


def pose_banner(snap, wall_of=None) -> str:
    """The pose banner: VALID with FRE, predicted TRE and latency (each with its age), or why not
    (the figures blanked with "stale since ...": :mod:`monotracker.ui.freshness`)."""
    pose = snap.pose
    if snap.camera.error:
        return f"<div class='mt-banner-bad mt-wrap' id='mt-pose-banner'>CAMERA: {st._esc(snap.camera.error)}</div>"
    if pose is None or not snap.camera.running:
        what = "NO POSE: camera stopped, start the camera" if not snap.camera.running else "NO POSE YET"
        return f"<div class='mt-banner-bad mt-wrap' id='mt-pose-banner'>{what}</div>"
    f = pose_figures(snap)
    if f["fre"].live:
        return (f"<div class='mt-banner-ok mt-wrap' id='mt-pose-banner'>POSE VALID: FRE {figure_html(f['fre'])}, "
                f"predicted TRE at target {figure_html(f['tre'])}, "
                f"{pose.n_visible} fiducials, latency {figure_html(f['reglat'])}{st.averaged_note(pose)}</div>")
    when = f["fre"]
    return (f"<div class='mt-banner-bad mt-wrap' id='mt-pose-banner'>POSE NOT VALID: {st._esc(pose_why(snap))}"
            f"<br>FRE {figure_html(when, wall_of)}</div>")


def validation_line(pose) -> str:
    """Live error at the validation fiducials (mm, point to viewing ray; engine/verification.py)
    and whether it allows arming; empty when the plan has no validation fiducials."""
    if pose is None or pose.validation_ok is None:
        return ""
    errs = ", ".join(f"#{fid} {fmt(e, ' mm', 2) if e is not None else 'not seen'}"
                     for fid, e in sorted(pose.validation_tre_mm.items()))
    ok = bool(pose.validation_ok)
    word = "VERIFIED" if ok else "NOT VERIFIED: arming refused"
    why = "" if ok or not pose.validation_reason else f" ({st._esc(pose.validation_reason)})"
    return (f"<div class='{'mt-banner-ok' if ok else 'mt-banner-bad'}' id='mt-validation' data-ok='{int(ok)}'>"
            f"Validation fiducials {word}: {errs}{why}</div>")


def recording_line(snap) -> str:
    """Session recording state (``--record``): folder, frames, dropped, error."""
    rec = snap.recording
    if rec is None:
        return ""
    state = "RECORDING" if rec.running else "recording stopped"
    extra = (f", {rec.dropped} dropped" if rec.dropped else "") + (f", {st._esc(rec.error)}" if rec.error else "")
    return f"<div class='mt-row' id='mt-recording'>{state}: {rec.frames} frames to {st._esc(rec.path)}{extra}</div>"


def registration_table(pose, snap=None, wall_of=None) -> str:
    """Per fiducial: its state and residual (px). The residuals are greyed with "stale since ..."
    when the pose is not trusted or too old (``snap`` given)."""
    if pose is None:
        return ""
    live, why = (True, "") if snap is None else residuals_live(snap)
    rows = []
    for fid, s in pose.fiducial_status.items():
        r = pose.residuals_px.get(fid)
        hidden = s in ("occluded", "newly_lost")
        col = "#c81e1e" if hidden else ("#1f8f3a" if s == "seen" else "#555")
        word = "HIDDEN (occluded)" if hidden else s
        res = fmt(r, ' px', 2) if live else f"<span class='mt-stale'>{fmt(r, ' px', 2)}</span>"
        rows.append(f"<tr><td><b>#{fid}</b></td><td style='color:{col}'><b>{word}</b></td><td>{res}</td></tr>")
    hidden_ids = [fid for fid, s in pose.fiducial_status.items() if s in ("occluded", "newly_lost")]
    alert = ""
    if hidden_ids:
        alert = (f"<div class='mt-alert' id='mt-occlusion' style='background:#b7791f'>OCCLUSION: fiducial"
                 f"{'s' if len(hidden_ids) > 1 else ''} {', '.join(map(str, hidden_ids))} hidden from the camera</div>")
    stale = ""
    if not live:
        since = pose.trusted_t if snap is not None else None
        when = "" if since is None or wall_of is None else time.strftime(" since %H:%M:%S", time.localtime(wall_of(since)))
        stale = f"<div class='mt-row mt-stale mt-wrap' id='mt-reg-stale'>residuals stale{when}: {st._esc(why)}</div>"
    return (alert + stale + f"<table class='mt' id='mt-reg' data-live='{int(live)}'><tr><th>fiducial</th><th>camera</th><th>residual</th></tr>"
            + "".join(rows) + "</table>")
