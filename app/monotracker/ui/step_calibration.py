"""Calibrate (reached from step 3, Register) of one tab: guided camera intrinsics and guided
hand-eye, over the engine's :mod:`monotracker.engine.calibration_jobs`.

Intrinsics: board settings (chessboard inner corners ``cols x rows`` or ChArUco squares, square
and marker size in mm), **Capture view** takes the newest live camera frame; each view is accepted
or refused with the job's one-line reason; coverage feedback (which cells of a 3 x 3 image grid the
corners have reached, spread of board tilts in deg); **Solve intrinsics** shows the RMS and the
per-view reprojection error (px); **Save** writes the camera model (OpenCV YAML or JSON, by the
path's suffix); **Save and use for this camera** saves it and restarts the session camera with it.

Hand-eye (eye-to-hand, board on the flange): **Record pose + view** pairs the arm's current
needle-tip pose (sim or real arm; connected, DISARMED, at the first record) with the board seen by the camera (this tab's solved intrinsics
if any, else the session camera's model); **Solve hand-eye** shows the residuals per view in mm
and deg; **Save** writes the hand-eye JSON; **Save and apply** also sets it on the session.

Threads: capture (board detection) and solve run on one worker thread per tab, never on viser's
callback thread; their result goes to this tab's result line only (``view.say``). The jobs are
this tab's own (another tab calibrating does not mix its views in). Reading frames and the arm's
pose changes nothing in the session; saving to the session (camera, hand-eye) goes through
``view.session`` (the control-checked client session), so only the tab in control can apply.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np

from monotracker.errors import InputError, MonoTrackerError
from monotracker.ui import status as st

log = logging.getLogger(__name__)

BOARD_KINDS = ("chessboard", "ChArUco")


def parse_board(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6): chessboard inner corners or ChArUco squares (cols x rows)."""
    from monotracker.vision.calibration import parse_pattern

    return parse_pattern(text.strip())


def coverage_html(report, min_views: int) -> str:
    """A 3 x 3 grid (green: board corners reached that image cell), views and tilt spread."""
    cells = report.cells or []
    rows = "".join("<tr>" + "".join(
        f"<td style='width:26px;height:18px;background:{'#1f8f3a' if c else '#ddd'}'></td>" for c in row) + "</tr>"
        for row in cells)
    return (f"<div class='mt-row' id='mt-cal-coverage' data-views='{report.n_views}' "
            f"data-coverage='{report.coverage:.3f}' data-ready='{int(report.ready)}'>"
            f"Views <b>{report.n_views}</b> / {min_views} needed; image coverage <b>{100 * report.coverage:.0f} %</b>; "
            f"tilt spread <b>{report.tilt_deg:.0f}&deg;</b> (aim for 20-45&deg;)</div>"
            f"<table style='border-collapse:separate;border-spacing:2px'>{rows}</table>")


def intrinsics_html(res) -> str:
    if res is None:
        return ""
    K = res.camera.K
    per = "".join(f"<tr><td>{st._esc(k)}</td><td>{v:.3f} px</td></tr>" for k, v in res.per_view_rms_px.items())
    return (f"<div class='mt-banner-ok' id='mt-cal-intr' data-rms='{res.rms_px:.4f}'>SOLVED: RMS "
            f"{res.rms_px:.3f} px from {len(res.per_view_rms_px)} views; fx {K[0, 0]:.1f}, fy {K[1, 1]:.1f}, "
            f"cx {K[0, 2]:.1f}, cy {K[1, 2]:.1f} px</div>"
            f"<table class='mt'><tr><th>view</th><th>reprojection RMS</th></tr>{per}</table>")


def handeye_html(res) -> str:
    if res is None:
        return ""
    if not res.ok:
        return f"<div class='mt-banner-bad' id='mt-cal-he' data-ok='0'>HAND-EYE REFUSED: {st._esc(res.reason)}</div>"
    per = "".join(f"<tr><td>view {i + 1}</td><td>{t:.2f} mm</td><td>{r:.3f}&deg;</td></tr>"
                  for i, (t, r) in enumerate(zip(res.translation_residuals_mm, res.rotation_residuals_deg)))
    return (f"<div class='mt-banner-ok' id='mt-cal-he' data-ok='1' data-mm='{res.translation_rms_mm:.4f}' "
            f"data-deg='{res.rotation_rms_deg:.4f}'>SOLVED ({st._esc(res.method)}, {res.n_poses} poses): residual RMS "
            f"{res.translation_rms_mm:.2f} mm, {res.rotation_rms_deg:.3f}&deg;</div>"
            f"<table class='mt'><tr><th>view</th><th>translation</th><th>rotation</th></tr>{per}</table>")


class CalibrationStep:
    def __init__(self, view):
        self.view = view
        self.lock = threading.Lock()
        self.intr = None  # this tab's IntrinsicsJob (made at the first capture from the board fields)
        self.he = None  # this tab's HandEyeJob
        self._worker: threading.Thread | None = None
        self._busy = ""  # what the worker is doing ('' when idle)
        self._last_report = None
        self._last_he_report = None
        gui, session = view.gui, view.session
        home = Path(session.home)
        self.folder = gui.add_folder("Calibrate: camera and hand-eye")
        with self.folder:
            self.h_live = gui.add_image(np.zeros((54, 96, 3), np.uint8), label="live camera", format="jpeg")
            self.h_busy = gui.add_html("")
            with gui.add_folder("Camera intrinsics"):
                self.h_kind = gui.add_dropdown("Board", BOARD_KINDS, initial_value="chessboard")
                self.h_pattern = gui.add_text("Corners / squares (cols x rows)", "9x6",
                                              hint="chessboard: inner corners; ChArUco: squares")
                self.h_square = gui.add_number("Square (mm)", 25.0, min=0.1, max=500.0, step=0.1)
                self.h_marker = gui.add_number("Marker (mm, ChArUco)", 18.0, min=0.1, max=500.0, step=0.1)
                self.h_min = gui.add_number("Views needed", 10, min=3, max=60, step=1)
                b_cap = gui.add_button("Capture view", color="green")
                b_solve = gui.add_button("Solve intrinsics")
                b_reset = gui.add_button("Start over (new board settings)")
                self.h_cov = gui.add_html("")
                self.h_intr = gui.add_html("")
                self.h_cam_path = gui.add_text("Save camera to", str(home / "camera_calibration.yaml"),
                                               hint=".yaml/.yml (OpenCV) or .json")
                b_save = gui.add_button("Save camera calibration")
                b_use = gui.add_button("Save and use for this camera", color="orange")
            with gui.add_folder("Hand-eye (board on the flange)"):
                self.h_he_pattern = gui.add_text("Flange board corners (cols x rows)", "7x5")
                self.h_he_square = gui.add_number("Flange board square (mm)", 20.0, min=0.1, max=500.0, step=0.1)
                self.h_he_min = gui.add_number("Poses needed", 8, min=3, max=60, step=1)
                b_rec = gui.add_button("Record pose + view", color="green")
                b_he_solve = gui.add_button("Solve hand-eye")
                b_he_reset = gui.add_button("Start hand-eye over")
                self.h_he_info = gui.add_html("")
                self.h_he = gui.add_html("")
                self.h_he_path = gui.add_text("Save hand-eye to", str(home / "hand_eye.json"))
                b_he_save = gui.add_button("Save hand-eye")
                b_he_apply = gui.add_button("Save and apply hand-eye", color="orange")
            b_back = gui.add_button("Back to Register")

        for button, what, fn in ((b_cap, "Capture view", self._capture), (b_solve, "Solve intrinsics", self._solve),
                                 (b_rec, "Record pose", self._record), (b_he_solve, "Solve hand-eye", self._he_solve)):
            self._bind_background(button, what, fn)
        for button, what, fn in ((b_reset, "Intrinsics", self._reset_intr), (b_save, "Save camera", self._save_intr),
                                 (b_use, "Use camera calibration", self._use_intr), (b_he_reset, "Hand-eye", self._reset_he),
                                 (b_he_save, "Save hand-eye", self._save_he), (b_he_apply, "Apply hand-eye", self._apply_he)):
            self._bind(button, what, fn)

        @b_back.on_click
        @view.safe("Back to Register")
        def _(_event) -> None:
            view.goto("register")

    # ------------------------------------------------------------------ plumbing
    def _bind(self, button, what: str, fn) -> None:
        view = self.view

        @button.on_click
        @view.safe(what)
        def _(_event) -> None:
            self._guarded(what, fn)

    def _bind_background(self, button, what: str, fn) -> None:
        view = self.view

        @button.on_click
        @view.safe(what)
        def _(_event) -> None:
            self.background(what, fn)

    def _guarded(self, what: str, fn) -> None:
        """Run ``fn() -> (ok, text)``; bad input (InputError, an unwritable path) is one line."""
        try:
            ok, text = fn()
        except (InputError, MonoTrackerError, OSError, ValueError) as exc:
            ok, text = False, str(exc)
        except Exception as exc:  # the operator sees one line, the log the traceback
            log.exception("calibration %s failed", what)
            ok, text = False, f"internal error ({type(exc).__name__}: {exc})"
        self.view.say(ok, f"{what}: {text}")

    def background(self, what: str, fn) -> bool:
        """Run ``fn`` on this tab's worker thread (one job at a time); its result on this tab."""
        with self.lock:
            if self._worker is not None and self._worker.is_alive():
                busy = self._busy
                refused = True
            else:
                refused = False
                self._busy = what
                self._worker = threading.Thread(target=self._work, args=(what, fn), daemon=True,
                                                name=f"monotracker-calib-{self.view.client_id}")
                self._worker.start()
        if refused:
            self.view.say(False, f"{what}: busy with {busy.lower()}; wait for it to finish")
        return not refused

    def _work(self, what: str, fn) -> None:
        try:
            self._guarded(what, fn)
        finally:
            with self.lock:
                self._busy = ""

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Wait for the worker (tests, shutdown); True when idle."""
        th = self._worker
        if th is not None:
            th.join(timeout)
        return th is None or not th.is_alive()

    # ------------------------------------------------------------------ intrinsics
    def _new_intrinsics_job(self):
        from monotracker.engine.calibration_jobs import IntrinsicsJob

        dims = parse_board(self.h_pattern.value)
        square = float(self.h_square.value)
        n = int(self.h_min.value)
        if self.h_kind.value == "ChArUco":
            return IntrinsicsJob(squares=dims, square_mm=square, marker_mm=float(self.h_marker.value), min_views=n)
        return IntrinsicsJob(pattern=dims, square_mm=square, min_views=n)

    def _capture(self):
        with self.lock:
            job = self.intr
        if job is None:
            job = self._new_intrinsics_job()
            with self.lock:
                self.intr = job
        r = job.capture(self.view.session)
        with self.lock:
            self._last_report = r
        return r.accepted, ("accepted: " if r.accepted else "refused: ") + r.reason

    def _solve(self):
        with self.lock:
            job = self.intr
        if job is None:
            raise InputError("capture views of the board first")
        res = job.solve()
        return True, f"RMS {res.rms_px:.3f} px over {len(res.per_view_rms_px)} views"

    def _reset_intr(self):
        with self.lock:
            self.intr, self._last_report = None, None
        return True, "views cleared; the next capture uses the board settings above"

    def _save_intr(self):
        with self.lock:
            job = self.intr
        if job is None or job.result is None:
            raise InputError("solve the calibration before saving it")
        p = job.save(self._path(self.h_cam_path.value))
        return True, f"saved to {p}"

    def _use_intr(self):
        ok, text = self._save_intr()
        path = text.removeprefix("saved to ")
        session = self.view.session
        snap = session.snapshot()
        was_running = snap.camera.running
        for what, fn, args in (("stop camera", session.stop_camera, ()),
                               ("set camera", session.set_camera, (snap.camera.source, path)),
                               ("start camera", session.start_camera, ())):
            if what == "start camera" and not was_running:
                break
            r = fn(*args)
            if not r.ok:
                return False, f"saved to {path}, but {what} refused: {r.message}"
        return True, f"saved to {path}; camera {snap.camera.source} now uses it" + ("" if was_running else
                                                                                    " (start the camera)")

    @staticmethod
    def _path(text: str) -> Path:
        text = (text or "").strip()
        if not text:
            raise InputError("type a file path to save to")
        p = Path(text).expanduser()
        if not p.parent.is_dir():
            raise InputError(f"folder not found: {p.parent}")
        return p

    # ------------------------------------------------------------------ hand-eye
    def _camera_model(self):
        """This tab's solved intrinsics if they fit the live camera, else the session camera's model."""
        from monotracker.vision.camera_model import CameraModel

        snap = self.view.session.snapshot()
        with self.lock:
            job = self.intr
        res = None if job is None else job.result
        size = None if snap.camera.image_size is None else tuple(int(v) for v in snap.camera.image_size)
        if res is not None and (size is None or tuple(res.camera.image_size) == size):
            return res.camera, "this page's intrinsics"
        if snap.camera.K is None or size is None:
            raise InputError("no camera model: start the camera (or solve the intrinsics) first")
        return CameraModel(np.asarray(snap.camera.K, float), np.asarray(snap.camera.dist, float), size), \
            "the session camera's calibration"

    def _record(self):
        from monotracker.engine.calibration_jobs import HandEyeJob

        if not self.view.session.snapshot().robot.connected:
            c = self.view.session.connect_robot()  # a command: only the tab in control
            if not c.ok:
                return False, f"cannot connect the arm: {c.message}"
        with self.lock:
            job = self.he
        if job is None:
            cam, where = self._camera_model()
            job = HandEyeJob(cam, pattern=parse_board(self.h_he_pattern.value), square_mm=float(self.h_he_square.value),
                             min_views=int(self.h_he_min.value))
            job.camera_from = where
            with self.lock:
                self.he = job
        # reads only (newest frame, the arm's pose): the engine session itself, not the control proxy
        r = job.capture(self.view.app.session)
        with self.lock:
            self._last_he_report = r
        return r.accepted, ("accepted: " if r.accepted else "refused: ") + r.reason

    def _he_solve(self):
        with self.lock:
            job = self.he
        if job is None:
            raise InputError("record robot poses with the board first")
        res = job.solve()
        if not res.ok:
            return False, res.reason
        return True, f"residual RMS {res.translation_rms_mm:.2f} mm, {res.rotation_rms_deg:.3f} deg over {res.n_poses} poses"

    def _reset_he(self):
        with self.lock:
            self.he, self._last_he_report = None, None
        return True, "poses cleared"

    def _save_he(self):
        with self.lock:
            job = self.he
        if job is None or job.result is None:
            raise InputError("solve the hand-eye calibration before saving it")
        if not job.result.ok:
            raise InputError(f"the hand-eye solve was refused ({job.result.reason}); nothing to save")
        p = job.save(self._path(self.h_he_path.value))
        return True, f"saved to {p}"

    def _apply_he(self):
        ok, text = self._save_he()
        with self.lock:
            T = np.asarray(self.he.result.T_base_cam_mm, float)
        r = self.view.session.set_hand_eye(T)
        if not r.ok:
            return False, f"{text}, but not applied: {r.message}"
        return True, f"{text}; applied to the session"

    # ------------------------------------------------------------------ render thread
    def show_frame(self, jpeg: bytes) -> None:
        """The shared live JPEG (see ``RegisterStep.show_frame``)."""
        self.h_live._format = "jpeg"
        self.h_live._data = jpeg

    def render(self, snap) -> None:
        with self.lock:
            busy, intr, he = self._busy, self.intr, self.he
            rep, he_rep = self._last_report, self._last_he_report
        self.h_busy.content = (f"<div class='mt-row' id='mt-cal-busy' data-busy='1'><b>{st._esc(busy)}...</b></div>"
                               if busy else "<div id='mt-cal-busy' data-busy='0'></div>")
        if intr is not None:
            r = intr.status()
            last = "" if rep is None else (f"<div class='mt-row' id='mt-cal-last' data-accepted='{int(rep.accepted)}'>"
                                           f"Last view: {'accepted' if rep.accepted else 'REFUSED'}: {st._esc(rep.reason)}</div>")
            self.h_cov.content = last + coverage_html(r, intr.min_views)
            self.h_intr.content = intrinsics_html(intr.result)
        else:
            self.h_cov.content = "<div class='mt-row' id='mt-cal-coverage' data-views='0'>No views yet: hold the board " \
                                 "in front of the camera and press Capture view.</div>"
            self.h_intr.content = ""
        if he is not None:
            n = len(he.views)
            last = "" if he_rep is None else (f"Last: {'accepted' if he_rep.accepted else 'REFUSED'}: "
                                              f"{st._esc(he_rep.reason)}<br>")
            self.h_he_info.content = (f"<div class='mt-row' id='mt-cal-poses' data-views='{n}'>{last}Poses <b>{n}</b> / "
                                      f"{he.min_views} needed; camera model: {st._esc(getattr(he, 'camera_from', ''))}"
                                      f"; robot {'connected' if snap.robot.connected else 'NOT CONNECTED'}</div>")
            self.h_he.content = handeye_html(he.result)
        else:
            self.h_he_info.content = ("<div class='mt-row' id='mt-cal-poses' data-views='0'>Fix the board to the flange, "
                                      "move the arm (rotate the wrist between poses) and press Record pose + view.</div>")
            self.h_he.content = ""


__all__ = ["CalibrationStep", "coverage_html", "handeye_html", "intrinsics_html", "parse_board"]
