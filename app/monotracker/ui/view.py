"""One browser client's page: its own step, fields, messages, 3D scene and engine proxy.

viser gives every connected browser tab a :class:`viser.ClientHandle` with its own ``gui`` and
``scene``; a :class:`ClientView` builds the whole page on that handle, so one tab never switches
another's step, overwrites its fields or shows its result line. Every command goes through
``session.for_client(client_id)``: the engine refuses it unless this tab is in control (STOP is
always allowed).

Threads: viser runs this view's callbacks on its worker threads; the app's render thread calls
:meth:`ClientView.render` at ~8 Hz and the overlay thread :meth:`ClientView.show_frame`. View
state (step, selected fiducial, scene keys) is guarded by ``self.lock``.
"""

from __future__ import annotations

import functools
import logging
import threading
import time

from monotracker.ui import status as st
from monotracker.ui.live_panel import DOCK_EDGE_PX, MAIN_LIVE_STEPS, shown_width
from monotracker.ui.page_width import PageWidth
from monotracker.ui.status import PANEL_PX, PANEL_PX_WIDE, WIDE_PX

log = logging.getLogger(__name__)

VIEW_STEPS = ("ct", "plan", "register", "robot")
STEP_LABELS = {"ct": "1 CT", "plan": "2 Plan", "register": "3 Register", "robot": "4 Robot"}
LABEL_STEPS = {v: k for k, v in STEP_LABELS.items()}
LIVE_STEPS = ("register", "robot", "calibration")  # steps whose page shows the live camera overlay


#: on a compact page the state block's words shrink a little so they fit the narrower status panel
COMPACT_CSS = ("<style>@media (max-width: 1600px) { .mt-state b { font-size: 1.7rem; } "
               ".mt-state span { font-size: 0.85rem; } }</style>")


def panel_widths(step: str, wide: bool) -> tuple[int, int]:
    """(status panel, step panel) widths in px for ``step`` on a compact or wide screen."""
    px = PANEL_PX_WIDE if wide else PANEL_PX
    if step in MAIN_LIVE_STEPS:
        return px["status"], px["steps_main_live"]
    return px["status"], px["steps_live"] if step in LIVE_STEPS else px["steps"]


def is_wide(viewport_px: float | None, wide_now: bool) -> bool:
    """Whether the page is wide enough for the wide panels (with hysteresis)."""
    if viewport_px is None:
        return wide_now
    return viewport_px >= WIDE_PX[0] if wide_now else viewport_px >= WIDE_PX[1]


def station_label(app, client_id) -> str:
    """This tab's name for the others: "station at <its IP address> (tab N)", or "station N"
    when the address is not known (viser keeps it on its websocket connection)."""
    try:
        conn = app.server._websock_server._live_connections.get(client_id)
        host = conn.remote_address[0] if conn is not None and conn.remote_address else None
    except Exception:  # noqa: BLE001 - a viser without that attribute: the plain name
        host = None
    return f"station at {host} (tab {client_id})" if host else f"station {client_id}"


def first_message(snap, notice: str | None) -> tuple[bool, str]:
    """The result line a fresh page starts with, true to the session's state (a CT loaded by
    ``--sample`` or a restored plan is not "start with step 1")."""
    if notice:
        return True, notice
    job = snap.job
    if job is not None and not job.done:
        return True, f"{job.message} ({100 * job.progress:.0f} %)"
    if job is not None and job.error:
        return False, f"CT: {job.error}"
    if snap.ct is None and snap.plan_ct_path and (job is None or job.done):
        return True, "Saved plan restored without its CT in memory: press \"Reload the plan's CT\" (step 1)."
    if snap.ct is None and not snap.fiducials:
        return True, "Ready. Start with step 1: load a CT."
    if not snap.fiducials_locked:
        return True, "CT loaded: check each fiducial, then lock the set."
    if not snap.plan.complete:
        return True, "Fiducials locked: plan the entry and the target (step 2)."
    return True, "Plan ready: register the camera (step 3)."


class ClientView:
    """The page of one browser client (``client``: a :class:`viser.ClientHandle`)."""

    def __init__(self, app, client):
        from monotracker.ui.live_panel import LivePanel
        from monotracker.ui.navigation_panel import NavigationScene
        from monotracker.ui.scene import SceneView
        from monotracker.ui.status_panel import StatusPanel
        from monotracker.ui.step_calibration import CalibrationStep
        from monotracker.ui.step_ct import CtStep
        from monotracker.ui.step_plan import PlanStep
        from monotracker.ui.step_register import RegisterStep
        from monotracker.ui.step_robot import RobotStep

        self.app = app
        self.client = client
        self.client_id = str(client.client_id)
        self.label = station_label(app, client.client_id)
        self.session = app.session.for_client(self.client_id)
        self.gui, self.scene = client.gui, client.scene
        self.lock = threading.RLock()
        #: the tab went away (:meth:`close`): the render and overlay threads leave its handles
        #: alone from then on (viser warns of every message queued on a closed connection)
        self.closed = False
        snap = self.session.snapshot()
        self.step: str = snap.step
        self._last_session_step = snap.step
        self.selected_fid = 0
        self.scene_keys: dict = {}
        self._msg_seq = 0
        self._panel_width = None  # (status px, steps px) last set
        self._wide = False
        self._last_image_size = None  # the camera's (w, h) px last rendered (the live panel's aspect)
        self._canvas = None  # the 3D canvas (w, h) CSS px between the docked panels, as the page reported it
        self._widths_set_at = 0.0  # wall time the docked panels' widths were last set
        # what this tab last saw: a change made elsewhere (control moved, STOP) is told on its result line
        self._seen_control = snap.control.controller
        self._seen_state = snap.robot.state
        self._job_watch = False  # this tab started a CT job: report its end on the result line
        self.notice = app.notice
        self.nav_scene = NavigationScene(self)  # the navigation view's worker (slices in the canvas)
        self.page_width = PageWidth(client)  # the page's CSS width (the compact / wide switch)

        gui = self.gui
        gui.configure_theme(control_width="large", show_share_button=False, brand_color=(43, 108, 176))
        gui.set_panel_label("MonoTracker")
        gui.add_html(st.CSS)
        gui.add_html(COMPACT_CSS)
        self.status = StatusPanel(self, snap)
        self.h_steps = gui.add_button_group("Step", [STEP_LABELS[s] for s in VIEW_STEPS])

        @self.h_steps.on_click
        @self.safe("Step")
        def _(event) -> None:
            self.goto(LABEL_STEPS.get(event.target.value, "ct"))

        self.h_live_main = gui.add_checkbox("Live image in the main view", True,
                                            hint="Register / Robot: the live overlay over the 3D view; "
                                                 "untick to see the 3D view whole")

        @self.h_live_main.on_update
        @self.safe("Live image")
        def _(_event) -> None:
            self.show_step()

        self.live = LivePanel(self)
        self.steps = {"ct": CtStep(self), "plan": PlanStep(self), "register": RegisterStep(self), "robot": RobotStep(self),
                      "calibration": CalibrationStep(self)}  # reached from Register
        self.scene3d = SceneView(self)
        gui.main_panel.dock_right()
        self.show_step()
        self.say(*first_message(snap, self.notice))
        self.scene3d.aim(self.step, snap)

    # ------------------------------------------------------------------ commands
    def say(self, ok: bool, text: str) -> None:
        """Show ``text`` on this tab's result line (green tick or red cross); nothing once the
        tab is gone (a line said to a closed connection only earns viser's warning)."""
        if self.gone:
            return
        with self.lock:
            self._msg_seq += 1
            seq = self._msg_seq
        self.status.h_msg.content = st.message_html(ok, text, seq)

    def run(self, what: str, fn, *args):
        """Call one session command, show its result on this tab; never lets an exception escape."""
        try:
            r = fn(*args)
        except Exception as exc:  # the operator sees one line, the log the traceback
            log.exception("command %s failed", what)
            self.say(False, f"{what}: internal error ({type(exc).__name__}: {exc})")
            return None
        ok = bool(getattr(r, "ok", True))
        msg = getattr(r, "message", "") or ("done" if ok else "failed")
        self.say(ok, f"{what}: {msg}")
        with self.lock:
            self.scene_keys.pop(("slices", self.step), None)
        return r

    def safe(self, what: str):
        """Decorator for a viser callback: an unexpected exception becomes one line on this tab
        (and a traceback in the log), never a dead button."""

        def wrap(fn):
            @functools.wraps(fn)
            def cb(event):
                try:
                    return fn(event)
                except Exception as exc:
                    log.exception("callback %s failed", what)
                    self.say(False, f"{what}: internal error ({type(exc).__name__}: {exc})")
                    return None

            return cb

        return wrap

    def watch_job(self) -> None:
        """This tab started a CT job: its end (done or failed) replaces the result line."""
        with self.lock:
            self._job_watch = True

    # ------------------------------------------------------------------ steps
    def goto(self, step: str) -> None:
        """Show ``step`` on this tab only."""
        with self.lock:
            self.step = step
            self.scene_keys.clear()
        self.show_step()

    def show_step(self) -> None:
        with self.lock:
            step = self.step
        for k, s in self.steps.items():
            s.folder.visible = k == step
        # the live camera is the view that matters in Register / Robot: a wider step panel there;
        # the panels grow on a wide screen (the browser's canvas width + the panels = the page)
        with self.lock:
            # the page's own CSS width (ui/page_width.py): the canvas's size in the camera
            # message is in drawing-buffer px (x devicePixelRatio x an adaptive 0.75-1), which read
            # a 1440 px page on a HiDPI screen as ~1800-2100 px and picked the wide panels
            viewport, canvas = self.page_width.width, None
            try:
                cam = self.client.camera
                if (viewport is not None and self._panel_width is not None and cam.update_timestamp
                        and cam.image_width > 0 and cam.image_height > 0
                        and cam.update_timestamp > self._widths_set_at):
                    # the canvas between the docked panels in CSS px, once the page's report
                    # reflects the panel widths now set (a width change reaches the page, then
                    # its canvas size comes back); its height from the canvas's aspect
                    w = viewport - sum(self._panel_width) - 2 * DOCK_EDGE_PX
                    if w > 0:
                        canvas = (int(w), int(w * cam.image_height / cam.image_width))
            except Exception:  # noqa: BLE001 - no camera message from the browser yet
                canvas = None
            self._wide = is_wide(viewport, self._wide)
            widths = panel_widths(step, self._wide)
            tick = step in MAIN_LIVE_STEPS
            if self.h_live_main.visible != tick:  # every prop assignment is a message to the browser
                self.h_live_main.visible = tick
            if canvas is not None and widths == self._panel_width:
                self._canvas = canvas
            self.live.update(step, self.live_main_wanted(), widths, self._last_image_size)
            if widths == self._panel_width:
                return
            old = self._panel_width
            self._panel_width = widths
            self._widths_set_at = time.time()
        if old is None or widths[0] != old[0]:
            self.status.panel.set_width(widths[0])
        self.gui.main_panel.set_width(widths[1])

    # ------------------------------------------------------------------ render (render thread)
    def render(self, snap) -> None:
        """Bring this tab up to date with ``snap`` (nothing once the tab is closed; checked again
        between the parts, since the tab may close while they draw)."""
        if self.gone:
            return
        with self.lock:
            if snap.step != self._last_session_step:
                # the session went back (fiducials unlocked, new plan): show the step that now
                # needs work. Forward moves are the operator's (go-to buttons, the step bar).
                if snap.step in ("ct", "plan") and VIEW_STEPS.index(snap.step) < VIEW_STEPS.index(self.step):
                    self.step = snap.step
                    self.scene_keys.clear()
                self._last_session_step = snap.step
            step = self.step
            report_job = self._job_watch and snap.job is not None and snap.job.done
            if report_job:
                self._job_watch = False
        for ok, text in self.changes_elsewhere(snap):
            self.say(ok, text)
        if report_job:
            if snap.job.error:
                self.say(False, f"CT: {snap.job.error}")
            else:
                self.say(True, f"CT loaded: {len(snap.fiducials)} fiducials found; check each, then lock the set")
        with self.lock:
            self._last_image_size = snap.camera.image_size
        if self.gone:
            return
        self.show_step()
        if snap.robot.state != "disarmed":
            self.notice = None
        for part in (lambda: self.status.render(snap, step), lambda: self.steps[step].render(snap),
                     lambda: self.scene3d.render(snap, step)):
            if self.gone:
                return
            part()

    @property
    def gone(self) -> bool:
        """The tab is closed (:meth:`close`) or its connection is: viser closes the connection and
        drops the client from ``get_clients()`` before it runs the disconnect callback (on its
        thread pool, later under load), and every update queued in between only earns a warning."""
        if self.closed:
            return True
        server = getattr(self.app, "server", None)
        return server is not None and self.client.client_id not in server.get_clients()

    def changes_elsewhere(self, snap) -> list[tuple[bool, str]]:
        """Result lines for what changed without this tab's command: control moved to another
        station (or away from this one), STOP pressed at another station (or by the engine)."""
        out = []
        with self.lock:
            prev_ctrl, prev_state = self._seen_control, self._seen_state
            self._seen_control, self._seen_state = snap.control.controller, snap.robot.state
        ctrl = snap.control.controller
        if ctrl != prev_ctrl and ctrl != self.client_id:
            who = (snap.control.controller_label or ctrl) if ctrl is not None else "nobody"
            if prev_ctrl == self.client_id:
                out.append((False, f"Control moved to {who}: this station is now viewing (Take control with the PIN)"))
            else:
                out.append((True, f"Control moved: {who} is in control now"))
        if snap.robot.state == "estopped" and prev_state not in (None, "estopped"):
            by = self.app.last_stop
            if by is None or time.time() - by[2] > 10.0:
                out.append((False, "Robot E-STOPPED (not from a station: see the alarms)"))
            elif by[0] != self.client_id:
                when = time.strftime("%H:%M:%S", time.localtime(by[2]))
                out.append((False, f"STOP pressed at {by[1]} at {when}: robot E-STOPPED"))
        return out

    def show_frame(self, jpeg: bytes) -> None:
        """The newest overlay frame (JPEG bytes, encoded once for all tabs) on the shown step."""
        if self.gone:
            return
        with self.lock:
            step = self.step
        if step in MAIN_LIVE_STEPS:
            self.live.show_frame(jpeg)
        elif step in LIVE_STEPS:
            self.steps[step].show_frame(jpeg)

    def nav_panel(self, step: str):
        """The navigation controls of ``step`` (a :class:`NavigationPanel`), or None."""
        return getattr(self.steps.get(step), "nav", None)

    @property
    def live_width(self) -> int:
        """The width (CSS px) this page shows the live image at, about: in Register / Robot the
        main view's (:func:`~monotracker.ui.live_panel.shown_width` from the canvas size the page
        reported, at least a compact page's; the stream caps it at its ``display_width``), in
        Calibrate the step panel's."""
        with self.lock:
            wide, step, canvas, size = self._wide, self.step, self._canvas, self._last_image_size
        if step in MAIN_LIVE_STEPS:
            px = PANEL_PX
            compact = 1280 - px["status"] - px["steps_main_live"] - 4
            aspect = 16 / 9 if not size else size[0] / max(1, size[1])
            return shown_width(canvas, aspect, compact)
        return (PANEL_PX_WIDE if wide else PANEL_PX)["steps_live"]

    @property
    def wants_live(self) -> bool:
        """Whether this tab shows the live image now: Calibrate, or Register / Robot with
        **Live image in the main view** ticked (no frame is encoded or sent for a hidden one)."""
        with self.lock:
            step = self.step
        if step in MAIN_LIVE_STEPS:
            return self.live_main_wanted()
        return step in LIVE_STEPS

    def live_main_wanted(self) -> bool:
        """The live image over the main view is wanted: **Live image in the main view** ticked, no
        ball-colour pick waiting for a click on the frame shown in the 3D view, and the shown
        step's **Slices in main view** not ticked (the live image would cover either)."""
        steps = getattr(self, "steps", None) or {}
        picker = getattr(steps.get("register"), "picker", None)
        with self.lock:
            step = self.step
        nav = getattr(steps.get(step), "nav", None)
        return (bool(self.h_live_main.value) and not (picker is not None and picker.active)
                and not (nav is not None and nav.active))

    def close(self) -> None:
        """The tab went away: give up control if it had it; nothing is drawn on it any more."""
        self.closed = True
        self.nav_scene.close()
        try:
            self.app.session.release_control(self.client_id)
        except Exception:
            log.exception("release control failed")

    def wall_time(self, snap, t_session: float) -> float:
        """Session clock time -> wall time (s since the epoch), for "since 12:03:07"."""
        return time.time() - (float(snap.t) - float(t_session))
