"""The MonoTracker web app: a viser page over one engine :class:`~monotracker.engine.Session`.

Every browser tab gets its own page (:class:`~monotracker.ui.view.ClientView`, built on viser's
per-client ``client.gui`` / ``client.scene``): its own step, fields, result line and 3D view,
driving the engine through ``session.for_client(client_id)`` so only the tab in control can
change anything (STOP works from every tab). The page of one tab:

* a status panel docked left (:mod:`~monotracker.ui.status_panel`): robot state, STOP (also the
  Space / Escape keys), who is in control and "Take control" (PIN pad), active alarms, camera,
  pose, the tab's last result;
* the step panel docked right: the 1 CT / 2 Plan / 3 Register / 4 Robot bar and the controls of
  the shown step only (``step_ct``, ``step_plan``, ``step_register``, ``step_robot``);
* the 3D view (:mod:`~monotracker.ui.scene`) in the frame the step needs.

Threads: viser runs callbacks on its worker threads; they only call Session commands (which
return at once). One render thread takes one ``session.snapshot()`` per tick (~8 Hz) and brings
every tab up to date; one overlay thread draws, downscales and JPEG-encodes each new camera frame
once per display width the tabs need (:mod:`~monotracker.ui.stream`: the width the page shows it
at, so no browser decodes pixels it cannot show) and hands the same bytes to every tab of that
width showing the live view.
Nothing here decides anything the headless demo does not: every decision is a Session method.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

import numpy as np
import viser

from monotracker.ui.stream import OverlayStream
from monotracker.ui.view import ClientView
from monotracker.ui.viser_threads import protect_client, protect_server, tab_caught_up

log = logging.getLogger(__name__)


class MonoTrackerApp:
    #: the longest the overlay waits for a tab to catch up before sending the newest frame anyway (s)
    MAX_HOLD_S = 0.25
    """The viser app. ``start()`` serves the page and starts the threads; ``stop()`` ends them
    (the session is shut down by its owner). ``stream_code``: stamp a frame-number barcode into
    the streamed image (benchmark only). ``display_width``: px width of the live overlay as sent
    to the browsers (frames are downscaled once for all tabs). ``login``: a
    :class:`~monotracker.ui.remote_login.LoginGate` (``serve --allow-remote``): viser then listens
    on 127.0.0.1 (an ephemeral port) and the login proxy on ``host:port``. ``environment_map``
    (True): viser's HDR environment map lights the 3D view besides the default lights; False: the
    default lights only. A browser without a GPU draws WebGL in software (SwiftShader), and the
    environment map (its prefiltered cube map and the shaders that sample it) cost it ~10 CPU s
    at each page load on the sample scene (4 CPU s without it; the browser tests turn it off:
    they check the page's logic, not its shading)."""

    def __init__(self, session, host: str = "127.0.0.1", port: int = 8080, *, stream_code: bool = False,
                 jpeg_quality: int = 80, max_stream_fps: float = 30.0, display_width: int = 960, login=None,
                 environment_map: bool = True):
        self.session = session
        self.host, self.port = host, int(port)
        self.login, self.proxy = login, None
        if login is None:
            self.server = viser.ViserServer(host=host, port=self.port, verbose=False)
        else:  # nothing reaches viser but through the login proxy (ui/remote_login.py)
            self.server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        self.stream = OverlayStream(display_width=display_width, jpeg_quality=jpeg_quality, stream_code=stream_code)
        self.max_stream_fps = float(max_stream_fps)
        self.environment_map = bool(environment_map)
        #: (client id, station label, wall time) of the newest STOP pressed in a tab, or None:
        #: every other tab says where STOP was pressed (ClientView.changes_elsewhere)
        self.last_stop: tuple | None = None
        self.frames_held = 0  # overlay waits for a tab to catch up (benchmark, tests)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._redraw = threading.Event()  # redraw every tab now (the robot's state changed)
        self._unsubscribe = None
        self._threads: list[threading.Thread] = []
        self._views: dict[int, ClientView] = {}
        self._history = deque(maxlen=600)  # (wall time s, tip error mm, speed mm/s)
        self.notice = None
        self._shown_snap = None  # the snapshot the tabs' panels show now (the overlay banner uses it too)
        snap = session.snapshot()
        if snap.fiducials or snap.plan.entry_lps_mm is not None:
            self.notice = f"Saved plan restored ({snap.plan_path}); robot starts DISARMED."
            if snap.ct is None and snap.plan_ct_path:
                self.notice += " Its CT is not loaded: \"Reload the plan's CT\" in step 1."

    # ================================================================== lifecycle
    def start(self) -> None:
        if self.login is not None:
            from monotracker.ui.remote_login import LoginProxy

            self.proxy = LoginProxy(self.login, self.host, self.port, self.server.get_port()).start()
        protect_server(self.server)  # viser's buffers are fed from several threads (ui/viser_threads.py)
        self.server.scene.world_axes.visible = False
        # no shadow pass: every 3D redraw costs a browser without a GPU one pass less (the live
        # image beside it gets the time; benchmarks/web_overlay.py)
        self.server.scene.configure_default_lights(enabled=True, cast_shadow=False)
        if not self.environment_map:
            self.server.scene.configure_environment_map(hdri=None)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        # a robot state change (a STOP acknowledged by the controller, from any tab or cause)
        # reaches every tab at once, not at the next render tick
        self._unsubscribe = self.session.subscribe(
            lambda ev: self.redraw_now() if getattr(ev, "code", "") in ("robot_state", "estop") else None)
        for name, fn in (("render", self._render_loop), ("overlay", self._overlay_loop)):
            th = threading.Thread(target=fn, name=f"monotracker-ui-{name}", daemon=True)
            th.start()
            self._threads.append(th)

    def stop(self) -> None:
        self._stop.set()
        self._redraw.set()
        if self._unsubscribe is not None:
            self._unsubscribe()
        for th in self._threads:
            th.join(timeout=2.0)
        if self.proxy is not None:
            self.proxy.stop()
        try:
            self.server.stop()
        except Exception:
            log.debug("viser stop failed", exc_info=True)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def views(self) -> list[ClientView]:
        """The pages of the connected tabs (a copy)."""
        with self._lock:
            return list(self._views.values())

    def history(self) -> list:
        with self._lock:
            return list(self._history)

    def _connect(self, client) -> None:
        protect_client(client)
        try:
            view = ClientView(self, client)
        except Exception:  # a tab that closes while its page is built
            log.exception("building the page for client %s failed", client.client_id)
            return
        with self._lock:
            self._views[client.client_id] = view

    def _disconnect(self, client) -> None:
        with self._lock:
            view = self._views.pop(client.client_id, None)
        if view is not None:
            view.close()
        else:
            self.session.release_control(str(client.client_id))

    # ================================================================== render loop
    def redraw_now(self) -> None:
        """Bring every tab up to date now rather than at the next tick (any thread)."""
        self._redraw.set()

    def _render_loop(self) -> None:
        period = 0.125
        while not self._stop.is_set():
            t0 = time.monotonic()
            self._redraw.clear()
            try:
                snap = self.session.snapshot()
                with self._lock:
                    self._shown_snap = snap
                if snap.robot.tip_error_mm is not None or snap.robot.state in ("tracking", "holding"):
                    with self._lock:
                        self._history.append((time.time(), snap.robot.tip_error_mm, snap.robot.speed_mm_s))
                for view in self.views():
                    try:
                        view.render(snap)
                    except Exception:  # keep the other tabs alive; the log has the traceback
                        log.exception("render failed for client %s", view.client_id)
            except Exception:
                log.exception("render failed")
            self._redraw.wait(max(0.01, period - (time.monotonic() - t0)))

    # ================================================================== overlay stream
    def _overlay_loop(self) -> None:
        """Draw + encode the newest camera frame once for all watching tabs, at most
        ``max_stream_fps``, and only when a watching tab has sent what was queued for it: a
        frame encoded while every tab still has one waiting would only replace it unseen (viser
        keeps the newest update per image), so that CPU goes to the tabs and the engine instead.
        A frame still goes out at least every ``MAX_HOLD_S`` (a tab that stopped reading must not
        freeze the others' view)."""
        last_index = None
        t_last = 0.0
        stopped_since = None  # wall time the camera was first seen stopped
        while not self._stop.is_set():
            try:
                watching = [v for v in self.views() if v.wants_live]
                fr = self.session.latest_frame() if watching else None
                if (watching and (fr is None or last_index is None or fr[1] == last_index)
                        and not self.shown_snapshot().camera.running):
                    # a stopped camera (no new frame) never leaves its last overlay up as if
                    # live: the last frame dimmed, no marks, "CAMERA STOPPED" (once a second:
                    # tabs that open meanwhile get it too)
                    stopped_since = stopped_since or time.time()
                    if time.monotonic() - t_last >= 1.0:
                        t_last = time.monotonic()
                        self.push_stopped(stopped_since, watching)
                    last_index = None if fr is None else fr[1]
                    self._stop.wait(0.05)
                    continue
                stopped_since = None
                if fr is None or fr[1] == last_index:
                    self._stop.wait(0.005)
                    continue
                now = time.monotonic()
                min_dt = 1.0 / self.max_stream_fps  # read each time: a tab (or a test) may lower it
                if now - t_last < min_dt:
                    self._stop.wait(min(0.1, min_dt - (now - t_last)))
                    continue
                if now - t_last < self.MAX_HOLD_S and not any(tab_caught_up(v.client) for v in watching):
                    self.frames_held += 1
                    self._stop.wait(0.004)
                    continue
                image, index, est = fr
                last_index = index
                t_last = time.monotonic()
                self.push_frame(image, est, self.shown_snapshot(), watching)
            except Exception:
                log.exception("overlay failed")
                self._stop.wait(0.2)

    def note_stop(self, client_id: str, label: str) -> None:
        """A tab pressed STOP (called on viser's event loop: one assignment, never blocks)."""
        self.last_stop = (client_id, label, time.time())

    def shown_snapshot(self):
        """The snapshot the panels show now (taken by the render thread), so the overlay's banner
        never disagrees with the panel beside it; a fresh one before the first render."""
        with self._lock:
            snap = self._shown_snap
        return snap if snap is not None else self.session.snapshot()

    def push_frame(self, image_bgr, estimate, snap, tabs=None) -> dict[int, bytes]:
        """Draw the overlay on one BGR frame and encode it once per display width the watching
        tabs need (``ClientView.live_width``: the width their page shows it at; tabs with the
        same layout share one encode), and show it on every tab watching (``tabs``, default:
        every tab on a live step). Returns {width px: JPEG bytes}."""
        if tabs is None:
            tabs = [v for v in self.views() if v.wants_live]
        groups: dict[int, list] = {}
        for view in tabs:
            groups.setdefault(self.stream.width_for(getattr(view, "live_width", None)), []).append(view)
        out = {}
        for width, group in groups.items():
            out[width] = self.stream.encode_frame(image_bgr, estimate, snap, width=width)
            self.push_jpeg(out[width], group)
        return out

    def push_stopped(self, since_wall: float, tabs) -> None:
        """"CAMERA STOPPED since HH:MM:SS" over the last frame (dimmed) on every tab in ``tabs``."""
        fr = self.session.latest_frame()
        image = None if fr is None else fr[0]
        text = f"CAMERA STOPPED since {time.strftime('%H:%M:%S', time.localtime(since_wall))}: no live image"
        groups: dict[int, list] = {}
        for view in tabs:
            groups.setdefault(self.stream.width_for(getattr(view, "live_width", None)), []).append(view)
        for width, group in groups.items():
            self.push_jpeg(self.stream.encode_stopped(image, text, width), group)

    def push_jpeg(self, jpeg: bytes, tabs=None) -> None:
        """The same encoded frame to ``tabs`` (default: every tab showing the live view). Handed
        over as a uint8 array view of the bytes: viser sends arrays raw after its zstd-compressed
        message, where bytes would be compressed again for every tab (and decompressed by every
        browser) for nothing."""
        data = np.frombuffer(jpeg, np.uint8)
        for view in (self.views() if tabs is None else tabs):
            if view.wants_live:
                view.show_frame(data)
