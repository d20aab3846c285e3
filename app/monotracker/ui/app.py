"""The MonoTracker web app: a viser page over one engine :class:`~monotracker.engine.Session`.

Layout (one step at a time, state always visible): the control panel on the right holds, from
top to bottom, the status banner (robot state in a big coloured block, workflow steps, camera,
pose, newest alert), the big red STOP button, the result of the last command, the step selector
(1 CT, 2 Plan, 3 Register, 4 Robot) and the controls of the selected step only. The 3D view
shows what that step needs, in the frame it needs:

* CT, Plan: CT LPS frame; head surface, numbered fiducials (green confirmed, yellow detected,
  red rejected), the path (entry cyan, target magenta); clicks on the head set what the
  "click on head" selector says (nothing, a new fiducial, the entry).
* Register: camera frame (OpenCV, z forward); camera frustum with the live image, the head,
  fiducials and path placed with the latest trusted ``T_cam_ct``.
* Robot: robot base frame; the UR10 drawn from its joint state, the camera (hand-eye), the
  head and path (``T_base_ct``), the needle tip.

Threads: viser runs callbacks on its worker threads; they only call Session commands (which
return at once) and record what the operator asked for under ``self._lock``. One render thread
polls ``session.snapshot()`` at ~8 Hz and updates the page; one overlay thread pushes the camera
image with the overlay drawn (JPEG) whenever a new frame exists. Nothing here decides anything
the headless demo does not: every decision is a Session method. Every error becomes a message in
the page; unexpected exceptions are logged with their traceback and shown as one line.

Units: the scene is in metres (viser's unit); CT/camera millimetres are scaled by 1e-3.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from pathlib import Path

import cv2
import numpy as np

from monotracker.geometry import apply_transform, invert_transform
from monotracker.ui import status as st
from monotracker.ui.overlay import draw_overlay, frame_code_strip
from monotracker.ui.slices import PLANES, render_slice

log = logging.getLogger(__name__)

MM = 1e-3  # scene metres per millimetre
VIEW_STEPS = ("ct", "plan", "register", "robot")
STEP_LABELS = {"ct": "1 CT", "plan": "2 Plan", "register": "3 Register", "robot": "4 Robot"}
LABEL_STEPS = {v: k for k, v in STEP_LABELS.items()}
CLICK_MODES = ("nothing", "add fiducial", "set entry", "set target")
FID_RGB = {"confirmed": (60, 200, 60), "added": (60, 200, 60), "detected": (240, 200, 0), "rejected": (220, 40, 40)}
CAMERA_SOURCES = ("sim", "sim-points", "device:0", "file:PATH", "folder:PATH")
FAULTS_UI = ("none", "occlude-all", "camera-freeze", "bad-pose", "robot-disconnect")


def _wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> quaternion (w, x, y, z)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


class _nullcontext:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def _fmt(v, unit="", nd=1) -> str:
    return "-" if v is None else f"{v:.{nd}f}{unit}"


class MonoTrackerApp:
    """The viser app. ``start()`` builds the page and the threads; ``stop()`` ends them (the
    session is shut down by its owner). ``stream_code``: stamp a frame-number barcode into the
    streamed image (benchmark only)."""

    def __init__(self, session, host: str = "127.0.0.1", port: int = 8080, *, stream_code: bool = False,
                 jpeg_quality: int = 80, max_stream_fps: float = 30.0):
        import viser

        self.session = session
        self.host, self.port = host, int(port)
        self.server = viser.ViserServer(host=host, port=self.port, verbose=False)
        self.stream_code = stream_code
        self.jpeg_quality = int(jpeg_quality)
        self.max_stream_fps = float(max_stream_fps)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._view_step: str | None = None
        self._auto_step = True
        self._last_session_step: str | None = None
        self._click_mode = "nothing"
        self._selected_fid = 0
        self._slice_request = None  # (point, fiducial key, plan key)
        self._slice_dirty = True
        self._scene_keys: dict = {}
        self._history = deque(maxlen=600)  # (t, tip error mm, speed mm/s)
        self._pushed: dict[int, float] = {}  # frame code -> wall time pushed (benchmark)
        self._push_count = 0
        self._notice = None
        self._msg_seq = 0
        snap = session.snapshot()
        if snap.fiducials or snap.plan.entry_lps_mm is not None:
            self._notice = f"Saved plan restored ({snap.plan_path}); robot starts DISARMED."

    # ================================================================== lifecycle
    def start(self) -> None:
        self._build_page()
        for name, fn in (("render", self._render_loop), ("overlay", self._overlay_loop)):
            th = threading.Thread(target=fn, name=f"monotracker-ui-{name}", daemon=True)
            th.start()
            self._threads.append(th)

    def stop(self) -> None:
        self._stop.set()
        for th in self._threads:
            th.join(timeout=2.0)
        try:
            self.server.stop()
        except Exception:  # noqa: BLE001
            log.debug("viser stop failed", exc_info=True)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    # ================================================================== commands (viser threads)
    def _say(self, ok: bool, text: str) -> None:
        with self._lock:
            self._msg_seq += 1
            seq = self._msg_seq
        self.h_msg.content = st.message_html(ok, text, seq)

    def _run(self, what: str, fn, *args):
        """Call one Session command, show its result; never lets an exception escape."""
        try:
            r = fn(*args)
        except Exception as exc:  # noqa: BLE001 - the operator sees one line, the log the traceback
            log.exception("command %s failed", what)
            self._say(False, f"{what}: internal error ({type(exc).__name__}: {exc})")
            return None
        ok = bool(getattr(r, "ok", True))
        msg = getattr(r, "message", "") or ("done" if ok else "failed")
        self._say(ok, f"{what}: {msg}")
        with self._lock:
            self._slice_dirty = True
        return r

    def _on(self, handle, what: str, fn):
        def cb(_event):
            try:
                fn()
            except Exception as exc:  # noqa: BLE001
                log.exception("callback %s failed", what)
                self._say(False, f"{what}: internal error ({type(exc).__name__}: {exc})")

        handle.on_click(cb)

    # ================================================================== page
    def _build_page(self) -> None:
        gui, scene = self.server.gui, self.server.scene
        try:
            gui.configure_theme(control_width="large", show_share_button=False, brand_color=(43, 108, 176))
        except TypeError:
            gui.configure_theme(control_width="large")
        try:
            gui.set_panel_label("MonoTracker")
        except Exception:  # noqa: BLE001
            pass
        scene.set_up_direction("+z")
        scene.world_axes.visible = False
        gui.add_html(st.CSS)
        snap = self.session.snapshot()
        # State, STOP and the last command's result live in their own docked panel so they stay
        # on screen however far the step's controls are scrolled.
        self.status_panel = None
        try:
            self.status_panel = gui.add_panel()
            tab = self.status_panel.add_tab("Status")
        except Exception:  # noqa: BLE001 - older viser: top of the control panel instead
            tab = None
            log.debug("no panels in this viser", exc_info=True)
        ctx = tab if tab is not None else _nullcontext()
        with ctx:
            self.h_status = gui.add_html(st.status_html(snap))
            self.h_stop = gui.add_button("STOP", color="red", hint="Emergency stop: the arm stops and stays stopped")
            self._on(self.h_stop, "STOP", lambda: self._run("STOP", self.session.estop))
            self.h_msg = gui.add_html(st.message_html(True, self._notice or "Ready. Start with step 1: load a CT."))
        if self.status_panel is not None:
            try:
                self.status_panel.dock_left()
                self.status_panel.set_width(430)
            except Exception:  # noqa: BLE001
                log.debug("status panel placement failed", exc_info=True)
        self.h_steps = gui.add_button_group("Step", [STEP_LABELS[s] for s in VIEW_STEPS])

        def on_step(event):
            with self._lock:
                self._view_step = LABEL_STEPS.get(event.target.value, "ct")
                self._auto_step = False
                self._scene_keys.clear()
                self._slice_dirty = True
            self._show_step()

        self.h_steps.on_click(on_step)
        self.folders = {}
        self._build_ct(gui)
        self._build_plan(gui)
        self._build_register(gui)
        self._build_robot(gui)
        self._view_step = snap.step
        self._last_session_step = snap.step
        self._show_step()
        try:
            gui.main_panel.dock_right()
            gui.main_panel.set_width(560)
        except Exception:  # noqa: BLE001 - older viser: floating panel
            log.debug("panel placement failed", exc_info=True)
        self.server.on_client_connect(lambda client: self._aim(client, self._view_step, self.session.snapshot()))

    def _aim(self, client, view, snap) -> None:
        """Point a browser's 3D camera at what the step shows (metres, world of that view)."""
        try:
            T_wc = self._world_from_ct(snap, view)
            centre = np.array([4.0, -12.0, 38.0])  # phantom head centre as a fallback, CT mm
            if snap.head_mesh is not None:
                v = np.asarray(snap.head_mesh.vertices)
                centre = (v.min(axis=0) + v.max(axis=0)) / 2
            if view in ("ct", "plan"):
                look = centre * MM
                pos = look + np.array([-0.22, -0.42, 0.22])
                up = (0.0, 0.0, 1.0)
            elif view == "register":
                look = apply_transform(T_wc, centre) * MM if T_wc is not None else np.array([0.0, 0.0, 0.4])
                pos = np.array([0.25, -0.2, -0.25])
                up = (0.0, -1.0, 0.0)
            else:
                look = apply_transform(T_wc, centre) * MM if T_wc is not None else np.array([0.6, 0.0, 0.3])
                pos = look + np.array([1.0, -1.4, 0.8])
                up = (0.0, 0.0, 1.0)
            with client.atomic():
                client.camera.up_direction = up
                client.camera.position = tuple(pos)
                client.camera.look_at = tuple(look)
        except Exception:  # noqa: BLE001
            log.debug("aim failed", exc_info=True)

    def _aim_all(self, view) -> None:
        snap = self.session.snapshot()
        for client in self.server.get_clients().values():
            self._aim(client, view, snap)

    def _show_step(self) -> None:
        for k, f in self.folders.items():
            f.visible = k == self._view_step

    # ------------------------------------------------------------------ CT step
    def _build_ct(self, gui) -> None:
        f = self.folders["ct"] = gui.add_folder("Step 1: CT and fiducials")
        with f:
            gui.add_markdown("Open the patient CT (a file or a DICOM folder), or the bundled sample. "
                             "Check each fiducial, then lock the set: nothing else can start before.")
            self.h_ct_path = gui.add_text("CT file or folder", "", hint="path on the server: .nii.gz, .nrrd, .mha or a DICOM folder")
            b_open = gui.add_button("Open CT", icon=None)
            self._on(b_open, "Open CT", lambda: self._run("Open CT", self.session.load_ct, self.h_ct_path.value.strip())
                     if self.h_ct_path.value.strip() else self._say(False, "Open CT: type the path of a CT file or folder first"))
            b_sample = gui.add_button("Load sample CT")
            self._on(b_sample, "Load sample CT", lambda: self._run("Load sample CT", self.session.load_sample_ct))
            self.h_progress = gui.add_progress_bar(0.0, visible=False, animated=True)
            self.h_job = gui.add_markdown("")
            self.h_fid_table = gui.add_html("")
            self.h_fid_sel = gui.add_number("Fiducial number", 0, min=0, max=99, step=1)

            def sel(_e):
                with self._lock:
                    self._selected_fid = int(self.h_fid_sel.value)
                    self._slice_dirty = True

            self.h_fid_sel.on_update(sel)
            grp = gui.add_button_group("Selected fiducial", ["Confirm", "Reject", "Undo"])

            def on_fid(event):
                word = {"Confirm": "confirmed", "Reject": "rejected", "Undo": "detected"}[event.target.value]
                self._run(f"Fiducial {int(self.h_fid_sel.value)}", self.session.set_fiducial_status,
                          int(self.h_fid_sel.value), word)

            grp.on_click(on_fid)
            b_all = gui.add_button("Confirm all detected")
            self._on(b_all, "Confirm all detected", self._confirm_all)
            self.h_new_fid = gui.add_vector3("New fiducial (LPS mm)", (0.0, 0.0, 0.0), step=0.1)
            b_add = gui.add_button("Add fiducial here")
            self._on(b_add, "Add fiducial", lambda: self._run("Add fiducial", self.session.add_fiducial,
                                                               np.array(self.h_new_fid.value, float)))
            self.h_click_ct = gui.add_dropdown("Click on head", ("nothing", "add fiducial"), initial_value="nothing",
                                               hint="what a click on the 3D head surface does")
            self.h_click_ct.on_update(lambda e: self._set_click_mode(self.h_click_ct.value))
            b_lock = gui.add_button("Lock fiducials and go to Plan", color="green")
            self._on(b_lock, "Lock fiducials", self._lock_fiducials)
            b_unlock = gui.add_button("Unlock fiducials (edit)")
            self._on(b_unlock, "Unlock fiducials", lambda: self._run("Unlock fiducials", self.session.unlock_fiducials))
            gui.add_markdown("**Slices** through the selected fiducial (green confirmed, yellow to check, red rejected)")
            self.h_slices_ct = {p: gui.add_image(np.zeros((8, 8, 3), np.uint8), label=p, format="jpeg") for p in PLANES}

    def _confirm_all(self) -> None:
        snap = self.session.snapshot()
        ids = [f.id for f in snap.fiducials if f.status == "detected"]
        if not ids:
            self._say(False, "Confirm all detected: no detected fiducial waits for a decision")
            return
        for i in ids:
            r = self.session.set_fiducial_status(i, "confirmed")
            if not r.ok:
                self._say(False, f"Fiducial {i}: {r.message}")
                return
        self._say(True, f"Confirmed fiducials {', '.join(map(str, ids))}")
        with self._lock:
            self._slice_dirty = True

    def _lock_fiducials(self) -> None:
        r = self._run("Lock fiducials", self.session.confirm_fiducials)
        if r is not None and r.ok:
            self._goto("plan")

    def _goto(self, step: str) -> None:
        with self._lock:
            self._view_step = step
            self._auto_step = True
            self._scene_keys.clear()
            self._slice_dirty = True
        self._show_step()

    def _set_click_mode(self, mode: str) -> None:
        with self._lock:
            self._click_mode = mode

    # ------------------------------------------------------------------ Plan step
    def _build_plan(self, gui) -> None:
        f = self.folders["plan"] = gui.add_folder("Step 2: plan the path")
        with f:
            gui.add_markdown("Pick the **entry** on the skin and the **target** inside: click the head "
                             "(choose what the click sets below) or type LPS coordinates in mm.")
            self.h_click_plan = gui.add_dropdown("Click on head", ("nothing", "set entry"), initial_value="set entry")
            self.h_click_plan.on_update(lambda e: self._set_click_mode(self.h_click_plan.value))
            self.h_entry = gui.add_vector3("Entry (LPS mm)", (0.0, 0.0, 0.0), step=0.1)
            b_e = gui.add_button("Set entry")
            self._on(b_e, "Set entry", lambda: self._run("Set entry", self.session.set_entry, np.array(self.h_entry.value, float)))
            self.h_target = gui.add_vector3("Target (LPS mm)", (0.0, 0.0, 0.0), step=0.1)
            b_t = gui.add_button("Set target")
            self._on(b_t, "Set target", lambda: self._run("Set target", self.session.set_target, np.array(self.h_target.value, float)))
            b_s = gui.add_button("Use the sample plan")
            self._on(b_s, "Sample plan", lambda: self._run("Sample plan", self.session.use_sample_plan))
            self.h_plan_info = gui.add_html("")
            b_next = gui.add_button("Path is good: go to Register", color="green")
            self._on(b_next, "Go to Register", self._to_register)
            b_x = gui.add_button("Export to 3D Slicer (.mrk.json)")
            self._on(b_x, "Export", self._export)
            gui.add_markdown("**Slices** through the target (path: cyan entry, magenta target)")
            self.h_slices_plan = {p: gui.add_image(np.zeros((8, 8, 3), np.uint8), label=p, format="jpeg") for p in PLANES}

    def _to_register(self) -> None:
        snap = self.session.snapshot()
        if not snap.plan.complete:
            self._say(False, "Go to Register: set both the entry and the target first")
            return
        self._goto("register")
        self._say(True, "Path planned. Choose the camera and start it.")

    def _export(self) -> None:
        from monotracker.paths import data_dir

        folder = (self.session.home if hasattr(self.session, "home") else data_dir()) / "slicer"
        try:
            files = self.session.export_slicer_markups(folder)
        except Exception as exc:  # noqa: BLE001 - InputError or I/O: one line for the operator
            self._say(False, f"Export: {exc}")
            return
        self._say(True, "Exported " + ", ".join(str(p) for p in files))

    # ------------------------------------------------------------------ Register step
    def _build_register(self, gui) -> None:
        f = self.folders["register"] = gui.add_folder("Step 3: register (camera)")
        with f:
            src = self.session.config.camera
            opts = CAMERA_SOURCES if src in CAMERA_SOURCES else (src,) + CAMERA_SOURCES
            self.h_cam_src = gui.add_dropdown("Camera source", opts, initial_value=src)
            self.h_cam_path = gui.add_text("Video file / device / folder", "",
                                           hint="for file:PATH / folder:PATH / device:N")
            self.h_calib = gui.add_text("Calibration file", "", hint="OpenCV YAML/JSON; empty for the simulated camera")
            b_apply = gui.add_button("Use this camera")
            self._on(b_apply, "Camera", self._apply_camera)
            grp = gui.add_button_group("Camera", ["Start camera", "Stop camera"])

            def on_cam(event):
                if event.target.value == "Start camera":
                    self._run("Start camera", self.session.start_camera)
                else:
                    self._run("Stop camera", self.session.stop_camera)

            grp.on_click(on_cam)
            self.h_pose_banner = gui.add_html("")
            self.h_live = gui.add_image(np.zeros((72, 128, 3), np.uint8), label="live camera + overlay", format="jpeg",
                                        jpeg_quality=self.jpeg_quality)
            self.h_reg_table = gui.add_html("")
            self.h_fault = gui.add_dropdown("Simulate a fault (sim only)", FAULTS_UI, initial_value="none")
            b_f = gui.add_button("Inject fault")
            self._on(b_f, "Fault", lambda: self._run("Fault", self.session.inject_fault, self.h_fault.value))
            b_next = gui.add_button("Registration is good: go to Robot", color="green")
            self._on(b_next, "Go to Robot", lambda: self._goto("robot"))

    def _apply_camera(self) -> None:
        src = self.h_cam_src.value
        extra = self.h_cam_path.value.strip()
        if src.endswith(":PATH") or src.startswith("device:"):
            kind = src.split(":", 1)[0]
            if extra:
                src = f"{kind}:{extra}"
            elif src.endswith(":PATH"):
                self._say(False, f"Camera: type the {kind} path in 'Video file / device / folder'")
                return
        calib = self.h_calib.value.strip() or None
        if calib is not None and not Path(calib).exists():
            self._say(False, f"Camera: calibration file not found: {calib}")
            return
        self._run("Camera", self.session.set_camera, src, calib)

    # ------------------------------------------------------------------ Robot step
    def _build_robot(self, gui) -> None:
        from monotracker.ui import plots

        f = self.folders["robot"] = gui.add_folder("Step 4: robot")
        with f:
            self.h_pin = gui.add_text("Operator PIN", "", hint="the PIN set when the app was started")
            b_arm = gui.add_button("Arm", color="orange")

            def arm():
                pin = self.h_pin.value.strip()
                self.h_pin.value = ""
                if not pin:
                    self._say(False, "Arm: type the operator PIN first")
                    return
                self._run("Arm", self.session.arm, pin)

            self._on(b_arm, "Arm", arm)
            b_dis = gui.add_button("Disarm")
            self._on(b_dis, "Disarm", lambda: self._run("Disarm", self.session.disarm))
            b_start = gui.add_button("Start tracking", color="green")
            self._on(b_start, "Start tracking", lambda: self._run("Start tracking", self.session.start_tracking))
            b_stop = gui.add_button("Stop tracking", color="yellow")
            self._on(b_stop, "Stop tracking", lambda: self._run("Stop tracking", self.session.stop_tracking))
            b_reset = gui.add_button("Reset e-stop")
            self._on(b_reset, "Reset e-stop", lambda: self._run("Reset e-stop", self.session.reset_estop))
            self.h_robot_info = gui.add_html("")
            self.h_plot = plots.add_tracking_plot(gui)

    # ================================================================== render loop
    def _render_loop(self) -> None:
        period = 0.125
        while not self._stop.is_set():
            t0 = time.monotonic()
            try:
                self._render_once()
            except Exception:  # noqa: BLE001 - keep the page alive; the log has the traceback
                log.exception("render failed")
            self._stop.wait(max(0.01, period - (time.monotonic() - t0)))

    def _render_once(self) -> None:
        snap = self.session.snapshot()
        with self._lock:
            if snap.step != self._last_session_step:
                # the session went back (e.g. fiducials unlocked, new plan): show the step that now
                # needs work. Forward moves are the operator's (the "go to" buttons, the step bar).
                # (register <-> robot flickers with the pose's trust: not a reason to move the view)
                if snap.step in ("ct", "plan") and VIEW_STEPS.index(snap.step) < VIEW_STEPS.index(self._view_step or "ct"):
                    self._view_step = snap.step
                    self._auto_step = True
                    self._scene_keys.clear()
                    self._slice_dirty = True
                self._last_session_step = snap.step
            view = self._view_step
        self._show_step()
        self.h_status.content = st.status_html(snap, view_step=view, notice=self._notice)
        if snap.robot.state != "disarmed":
            self._notice = None
        if snap.robot.tip_error_mm is not None or snap.robot.state in ("tracking", "holding"):
            self._history.append((time.time(), snap.robot.tip_error_mm, snap.robot.speed_mm_s))
        if view == "ct":
            self._render_ct_panel(snap)
        elif view == "plan":
            self._render_plan_panel(snap)
        elif view == "register":
            self._render_register_panel(snap)
        else:
            self._render_robot_panel(snap)
        self._render_scene(snap, view)

    # ------------------------------------------------------------------ panels
    def _render_ct_panel(self, snap) -> None:
        job = snap.job
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
        self.h_fid_table.content = self._fiducial_table(snap)
        self._render_slices(snap, self.h_slices_ct, "ct")

    def _fiducial_table(self, snap) -> str:
        if not snap.fiducials:
            return ""
        lock = ("<b style='color:#1f8f3a'>LOCKED</b>" if snap.fiducials_locked else
                "<b style='color:#b7791f'>not locked: confirm or reject each, then lock</b>")
        rows = []
        for f in snap.fiducials:
            col = "#%02x%02x%02x" % FID_RGB.get(f.status, (0, 0, 0))
            c = f.centre_lps_mm
            rows.append(f"<tr><td><b>{f.id}</b></td><td style='color:{col}'><b>{f.status}</b></td>"
                        f"<td>{c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}</td><td>{f.radius_mm:.1f}</td><td>{f.score:.2f}</td></tr>")
        n_ok = sum(f.status in ("confirmed", "added") for f in snap.fiducials)
        return (f"<div class='mt-row'>{len(snap.fiducials)} fiducials, {n_ok} confirmed; {lock}</div>"
                "<table class='mt' id='mt-fiducials'><tr><th>#</th><th>status</th><th>centre LPS mm</th><th>r mm</th>"
                f"<th>score</th></tr>{''.join(rows)}</table>")

    def _plan_info(self, snap) -> str:
        from monotracker.engine.plan import distance_segment_to_points_mm

        p = snap.plan
        e, t = p.entry_lps_mm, p.target_lps_mm
        lines = [f"<div class='mt-row'>Entry: <b>{'-' if e is None else ', '.join(f'{v:.1f}' for v in e)}</b> mm LPS</div>",
                 f"<div class='mt-row'>Target: <b>{'-' if t is None else ', '.join(f'{v:.1f}' for v in t)}</b> mm LPS</div>"]
        if p.complete:
            lines.append(f"<div class='mt-row' id='mt-plan-metrics'>Length <b>{_fmt(p.path_length_mm, ' mm')}</b>, "
                         f"angle to skin normal <b>{_fmt(p.angle_to_skin_normal_deg, '&deg;')}</b>, "
                         f"closest fiducial <b>{_fmt(p.distance_to_fiducials_mm, ' mm')}</b></div>")
            rows = []
            for f in snap.fiducials:
                if f.status in ("confirmed", "added"):
                    d = distance_segment_to_points_mm(e, t, np.asarray(f.centre_lps_mm)[None, :])
                    rows.append(f"<td>#{f.id}: {float(np.min(d)):.1f}</td>")
            cells = "".join(rows)
            lines.append(f"<div class='mt-row'>Distance path to each fiducial (mm):</div><table class='mt'><tr>{cells}</tr></table>")
        return "".join(lines)

    def _render_plan_panel(self, snap) -> None:
        self.h_plan_info.content = self._plan_info(snap)
        # show the plan's points in the typed fields whenever the plan changes (not while typing)
        for key, handle, p in (("entry_sync", self.h_entry, snap.plan.entry_lps_mm),
                               ("target_sync", self.h_target, snap.plan.target_lps_mm)):
            val = None if p is None else tuple(round(float(v), 2) for v in p)
            if val is not None and self._scene_keys.get(key) != val:
                self._scene_keys[key] = val
                handle.value = val
        self._render_slices(snap, self.h_slices_plan, "plan")

    def _render_register_panel(self, snap) -> None:
        pose = snap.pose
        if snap.camera.error:
            self.h_pose_banner.content = f"<div class='mt-banner-bad'>CAMERA: {st._esc(snap.camera.error)}</div>"
        elif pose is None:
            self.h_pose_banner.content = ("<div class='mt-banner-bad' id='mt-pose-banner'>NO POSE: start the camera</div>"
                                          if not snap.camera.running else
                                          "<div class='mt-banner-bad' id='mt-pose-banner'>NO POSE YET</div>")
        elif pose.trusted:
            self.h_pose_banner.content = (f"<div class='mt-banner-ok' id='mt-pose-banner'>POSE VALID: FRE {_fmt(pose.fre_mm, ' mm', 2)}, "
                                          f"predicted TRE at target {_fmt(pose.predicted_tre_mm, ' mm', 2)}, "
                                          f"{pose.n_visible} fiducials, latency {_fmt(pose.latency_ms, ' ms', 0)}</div>")
        else:
            self.h_pose_banner.content = f"<div class='mt-banner-bad' id='mt-pose-banner'>POSE NOT VALID: {st._esc(pose.reason)}</div>"
        if pose is None:
            self.h_reg_table.content = ""
            return
        rows = []
        for fid, s in pose.fiducial_status.items():
            r = pose.residuals_px.get(fid)
            hidden = s in ("occluded", "newly_lost")
            col = "#c81e1e" if hidden else ("#1f8f3a" if s == "seen" else "#555")
            word = "HIDDEN (occluded)" if hidden else s
            rows.append(f"<tr><td><b>#{fid}</b></td><td style='color:{col}'><b>{word}</b></td>"
                        f"<td>{_fmt(r, ' px', 2)}</td></tr>")
        hidden_ids = [fid for fid, s in pose.fiducial_status.items() if s in ("occluded", "newly_lost")]
        alert = ""
        if hidden_ids:
            alert = (f"<div class='mt-alert' id='mt-occlusion' style='background:#b7791f'>OCCLUSION: fiducial"
                     f"{'s' if len(hidden_ids) > 1 else ''} {', '.join(map(str, hidden_ids))} hidden from the camera</div>")
        self.h_reg_table.content = (alert + "<table class='mt' id='mt-reg'><tr><th>fiducial</th><th>camera</th><th>residual</th></tr>"
                                    + "".join(rows) + "</table>")

    def _render_robot_panel(self, snap) -> None:
        r = snap.robot
        conn = "connected" if r.connected else "<b style='color:#c81e1e'>NOT CONNECTED</b>"
        self.h_robot_info.content = (
            f"<div class='mt-row'>Robot {conn}; {st._esc(r.message)}</div>"
            f"<div class='mt-row' id='mt-robot-metrics'>Tip error <b>{_fmt(r.tip_error_mm, ' mm', 2)}</b>, "
            f"angle error <b>{_fmt(r.angle_error_deg, '&deg;', 2)}</b>, speed <b>{_fmt(r.speed_mm_s, ' mm/s', 1)}</b>, "
            f"latency {_fmt(r.latency_ms, ' ms', 0)}</div>")
        from monotracker.ui import plots

        plots.update_tracking_plot(self.h_plot, list(self._history))

    # ------------------------------------------------------------------ slices
    def _volume(self):
        """The session's CT volume for the slice views (read-only use)."""
        return self.session.volume()

    def _render_slices(self, snap, handles, view) -> None:
        vol = self._volume()
        if vol is None:
            return
        if view == "plan" and snap.plan.target_lps_mm is not None:
            point = np.asarray(snap.plan.target_lps_mm)
        else:
            fid = next((f for f in snap.fiducials if f.id == self._selected_fid), None)
            point = np.asarray(fid.centre_lps_mm) if fid is not None else None
            if point is None:
                from monotracker.ui.slices import volume_bounds_lps

                lo, hi = volume_bounds_lps(vol)
                point = (lo + hi) / 2
        key = (view, id(vol), tuple(np.round(point, 2)), tuple((f.id, f.status) for f in snap.fiducials),
               None if snap.plan.entry_lps_mm is None else tuple(snap.plan.entry_lps_mm),
               None if snap.plan.target_lps_mm is None else tuple(snap.plan.target_lps_mm))
        if self._scene_keys.get(("slices", view)) == key:
            return
        self._scene_keys[("slices", view)] = key
        for plane in PLANES:
            img, _ = render_slice(vol, plane, point, snap.fiducials, snap.plan.entry_lps_mm, snap.plan.target_lps_mm)
            handles[plane].image = img

    # ------------------------------------------------------------------ 3D scene
    def _world_from_ct(self, snap, view):
        """``T_world_ct`` (mm) for this view, or None when the view cannot place the head."""
        if view in ("ct", "plan"):
            return np.eye(4)
        if view == "register":
            return None if snap.scene.T_cam_ct is None else np.asarray(snap.scene.T_cam_ct)
        return None if snap.scene.T_base_ct is None else np.asarray(snap.scene.T_base_ct)

    def _set_pose(self, handle, T_mm) -> None:
        handle.wxyz = _wxyz(T_mm[:3, :3])
        handle.position = T_mm[:3, 3] * MM

    def _render_scene(self, snap, view) -> None:
        scene = self.server.scene
        keys = self._scene_keys
        T_wc = self._world_from_ct(snap, view)
        # --- CT group: head, fiducials, path, in CT mm scaled to m, placed by T_world_ct
        if keys.get("view") != view or (T_wc is not None) != keys.get("placed"):
            keys["placed"] = T_wc is not None
            self._aim_all(view)
        if keys.get("view") != view:
            keys["view"] = view
            keys.pop("mesh", None)
            keys.pop("fids", None)
            keys.pop("path", None)
            keys.pop("robot_q", None)
            scene.reset()
            self._ct_frame = scene.add_frame("/ct", show_axes=False)
            self._cam_frame = scene.add_frame("/cam", show_axes=False, visible=view in ("register", "robot"))
            self._robot_frame = scene.add_frame("/robot", show_axes=False, visible=view == "robot")
        self._ct_frame.visible = T_wc is not None
        if T_wc is not None:
            self._set_pose(self._ct_frame, T_wc)
        mesh = snap.head_mesh
        if mesh is not None and keys.get("mesh") is not mesh:
            keys["mesh"] = mesh
            h = scene.add_mesh_simple("/ct/head", np.asarray(mesh.vertices) * MM, np.asarray(mesh.faces, np.int32),
                                      color=(230, 190, 160), opacity=0.55 if view != "ct" else 0.8,
                                      side="double", cast_shadow=False, receive_shadow=False)
            h.on_click(self._on_head_click)
        fkey = tuple((f.id, f.status, tuple(np.round(f.centre_lps_mm, 2))) for f in snap.fiducials)
        if keys.get("fids") != fkey:
            keys["fids"] = fkey
            _reset_group(scene, "/ct/fids")
            for f in snap.fiducials:
                c = np.asarray(f.centre_lps_mm) * MM
                scene.add_icosphere(f"/ct/fids/f{f.id}", radius=f.radius_mm * MM, color=FID_RGB.get(f.status, (200, 200, 200)),
                                    position=c, cast_shadow=False, receive_shadow=False)
                scene.add_label(f"/ct/fids/l{f.id}", str(f.id), position=c + np.array([0, 0, 1.6 * f.radius_mm * MM]))
        pkey = (None if snap.plan.entry_lps_mm is None else tuple(snap.plan.entry_lps_mm),
                None if snap.plan.target_lps_mm is None else tuple(snap.plan.target_lps_mm))
        if keys.get("path") != pkey:
            keys["path"] = pkey
            _reset_group(scene, "/ct/path")
            e, t = snap.plan.entry_lps_mm, snap.plan.target_lps_mm
            if e is not None:
                scene.add_icosphere("/ct/path/entry", radius=2.5 * MM, color=(0, 200, 255), position=np.asarray(e) * MM)
            if t is not None:
                scene.add_icosphere("/ct/path/target", radius=2.5 * MM, color=(255, 0, 255), position=np.asarray(t) * MM)
            if e is not None and t is not None:
                d = np.asarray(e) - np.asarray(t)
                ext = np.asarray(e) + 60.0 * d / np.linalg.norm(d)  # the needle's way out, 60 mm
                pts = np.array([[t, e], [e, ext]]) * MM
                cols = np.array([[[255, 0, 255], [0, 200, 255]], [[0, 200, 255], [0, 200, 255]]], np.uint8)
                scene.add_line_segments("/ct/path/line", pts, cols, thickness=4.0, thickness_units="screen")
        # --- camera
        if view in ("register", "robot"):
            T_w_cam = np.eye(4) if view == "register" else (None if snap.scene.T_base_cam is None else np.asarray(snap.scene.T_base_cam))
            self._cam_frame.visible = T_w_cam is not None
            if T_w_cam is not None:
                self._set_pose(self._cam_frame, T_w_cam)
                if "frustum" not in keys:
                    keys["frustum"] = True
                    K, size = snap.camera.K, snap.camera.image_size
                    if K is not None and size is not None:
                        fov = 2 * np.arctan2(size[1] / 2, K[1, 1])
                        aspect = size[0] / size[1]
                    else:
                        fov, aspect = np.radians(45), 16 / 9
                    self._frustum = scene.add_camera_frustum("/cam/frustum", fov=float(fov), aspect=float(aspect),
                                                             scale=0.06, thickness=0.0015, color=(40, 40, 200))
        # --- robot
        if view == "robot" and snap.scene.q is not None:
            q = np.asarray(snap.scene.q)
            if keys.get("robot_q") is None or np.abs(keys["robot_q"] - q).max() > 1e-4:
                keys["robot_q"] = q.copy()
                from monotracker.ui.robot_view import joint_chain_mm

                pts = joint_chain_mm(q) * MM
                segs = np.stack([pts[:-1], pts[1:]], axis=1)
                scene.add_line_segments("/robot/links", segs, (90, 110, 140), thickness=0.07)  # UR10 links ~ 7 cm across
                scene.add_point_cloud("/robot/joints", pts, colors=(40, 60, 90), point_size=0.05, point_shape="circle")
            if snap.scene.T_base_tip is not None:
                tip = np.asarray(snap.scene.T_base_tip)
                a = tip[:3, 3]
                b = a - 120.0 * tip[:3, 2]  # needle axis back along -z, 120 mm
                scene.add_line_segments("/robot/needle", np.array([[b, a]]) * MM, (250, 250, 250), thickness=5.0, thickness_units="screen")

    def _on_head_click(self, event) -> None:
        """A click on the head surface: add a fiducial / set the entry, per the selector."""
        try:
            with self._lock:
                mode = self._click_mode
                view = self._view_step
            if view not in ("ct", "plan") or mode == "nothing":
                return
            snap = self.session.snapshot()
            if snap.head_mesh is None:
                return
            p = self._pick_head(snap, np.asarray(event.ray_origin) / MM, np.asarray(event.ray_direction))
            if p is None:
                self._say(False, "Click: no skin under the pointer")
                return
            if mode == "add fiducial":
                # the picked surface point goes to the typed field: the operator checks it on the
                # slices and corrects it (a ball's centre lies one radius inside its surface)
                self.h_new_fid.value = tuple(float(v) for v in p)
                self._say(True, f"Picked ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm: check and press 'Add fiducial here'")
            elif mode == "set entry":
                self.h_entry.value = tuple(float(v) for v in p)
                self._run("Set entry", self.session.set_entry, p)
            elif mode == "set target":
                self.h_target.value = tuple(float(v) for v in p)
                self._run("Set target", self.session.set_target, p)
        except Exception as exc:  # noqa: BLE001
            log.exception("click failed")
            self._say(False, f"Click: internal error ({type(exc).__name__}: {exc})")

    def _pick_head(self, snap, origin_mm, direction):
        """First hit (CT LPS mm) of the click ray with the head surface (view frames are CT in
        the CT/Plan steps, so world = CT)."""
        import trimesh

        mesh = trimesh.Trimesh(np.asarray(snap.head_mesh.vertices), np.asarray(snap.head_mesh.faces), process=False)
        locs, _, _ = mesh.ray.intersects_location(origin_mm[None, :], direction[None, :] / np.linalg.norm(direction))
        if len(locs) == 0:
            return None
        return locs[np.argmin(np.linalg.norm(locs - origin_mm, axis=1))]

    # ================================================================== overlay stream
    def _overlay_loop(self) -> None:
        last_index = None
        min_dt = 1.0 / self.max_stream_fps
        t_last = 0.0
        while not self._stop.is_set():
            try:
                with self._lock:
                    view = self._view_step
                fr = self.session.latest_frame() if view == "register" else None
                if fr is None or fr[1] == last_index:
                    self._stop.wait(0.005)
                    continue
                now = time.monotonic()
                if now - t_last < min_dt:
                    self._stop.wait(min_dt - (now - t_last))
                    continue
                image, index, est = fr
                last_index = index
                t_last = time.monotonic()
                self.push_frame(image, est, self.session.snapshot())
            except Exception:  # noqa: BLE001
                log.exception("overlay failed")
                self._stop.wait(0.2)

    def push_frame(self, image_bgr: np.ndarray, estimate, snap) -> None:
        """Draw the overlay on one BGR frame and send it to the page (and the 3D frustum)."""
        img = draw_overlay(image_bgr, estimate, snap)
        self._push_count += 1
        if self.stream_code:
            strip = frame_code_strip(self._push_count)
            img[-strip.shape[0]:, :strip.shape[1]] = strip
            self._pushed[self._push_count] = time.time()
        self.h_live.image = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _reset_group(scene, name: str) -> None:
    """Empty the scene group ``name`` (remove it if present) and create it again, hidden axes."""
    try:
        scene.remove_by_name(name)
    except Exception:  # noqa: BLE001 - viser raises when the group does not exist yet
        pass
    scene.add_frame(name, show_axes=False)
