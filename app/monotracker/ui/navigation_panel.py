"""The navigation view of one tab: the views of :mod:`monotracker.ui.navigation` shown as
image tiles in the tab's main (3D) canvas, clickable.

* :class:`NavigationPanel`: the controls in a step's panel (Plan, Robot): main view 3D /
  Slices, window/level presets (bone, brain, soft tissue) and width / level sliders (HU), what
  a click on a slice does (centre the slices there, set entry, set target, add fiducial), and a
  line saying where the slices cut (``#mt-nav``: ``data-seq`` counts rendered sets,
  ``data-wl`` "W/L", ``data-source`` tip | target | picked | centre).
* :class:`NavigationScene`: one worker thread per tab renders the views (sampling, drawing,
  JPEG encoding) at most :data:`NAV_MAX_HZ` times a second and only when what they show
  changed; viser callbacks and the app's render thread only post requests to it. The tiles lie
  flat in the canvas (world plane z = 0, camera looking along +z with -y up) so each looks like
  a 2D viewer; a click on one is a ray that meets that plane at one pixel, and the pixel is an
  LPS point (:meth:`PlaneView.to_lps`) that goes to the Session's plan commands (the engine
  validates it). The browser may still show an earlier image than the newest geometry: a click
  is refused when the tile's recent geometries (:data:`CLICK_SETTLE_S`) disagree on its point.

Scene units are viser's (metres) but only the layout matters: a tile is :data:`TILE` wide.
"""

from __future__ import annotations

import html
import logging
import math
import threading
import time

import numpy as np

from monotracker.ui import navigation as nav
from monotracker.ui.slices import suggested_balls, volume_bounds_lps

log = logging.getLogger(__name__)

NAV_MAX_HZ = 4.0  # rendered sets per second per tab (sampling + JPEG of 5 images)
TILE = 0.2  # tile width in the canvas (scene units)
GAP = 0.012
CLICK_MODES = ("centre slices here", "set entry", "set target", "add fiducial", "nothing")
#: a click may have landed on an image sent up to this long before the click arrived (the browser
#: shows a new image a network round trip after it is sent): every geometry a tile had in that
#: window must map the click to the same point (within :data:`CLICK_TOL_MM`) or it is refused
CLICK_SETTLE_S = 1.0
CLICK_TOL_MM = 1.0


class NavigationPanel:
    """The navigation controls of one step (``key``: "plan" | "robot") of one tab, built in the
    current GUI container. ``live``: the slices follow the robot's needle tip when it is known."""

    def __init__(self, view, key: str, *, live: bool, click_default: str = "centre slices here"):
        self.view, self.key, self.live = view, key, live
        gui = view.gui
        self.lock = threading.Lock()
        self.active = False
        self.width, self.level = nav.WL_PRESETS["bone"]
        self.picked = None  # LPS mm, an operator's "centre slices here"
        self.h_main = gui.add_checkbox("Slices in main view", False,
                                       hint="the navigation view (CT slices) instead of the 3D view, this tab only")
        self.h_preset = gui.add_dropdown("Window preset", tuple(nav.WL_PRESETS), initial_value="bone")
        self.h_width = gui.add_slider("Window width (HU)", 1, 4000, 1, self.width)
        self.h_level = gui.add_slider("Window level (HU)", -1000, 3000, 1, self.level)
        self.h_click = gui.add_dropdown("Slice click", CLICK_MODES, initial_value=click_default,
                                        hint="what a click on a slice in the main view does")
        self.h_info = gui.add_html(info_html(key, 0, self.width, self.level, "", "Main view: 3D. Tick 'Slices in main view' for the navigation view."))

        @self.h_main.on_update
        @view.safe("Main view")
        def _(_event) -> None:
            with self.lock:
                self.active = bool(self.h_main.value)
            view.scene_keys.pop("view", None)  # the scene is rebuilt for the chosen view
            view.nav_scene.poke()
            view.show_step()  # Robot: the live image over the main view steps aside for the slices

        @self.h_preset.on_update
        @view.safe("Window preset")
        def _(_event) -> None:
            w, lv = nav.WL_PRESETS[self.h_preset.value]
            with self.lock:
                self.width, self.level = w, lv
            self.h_width.value, self.h_level.value = w, lv
            view.nav_scene.poke()

        for h in (self.h_width, self.h_level):
            @h.on_update
            @view.safe("Window")
            def _(_event) -> None:
                with self.lock:
                    self.width, self.level = float(self.h_width.value), float(self.h_level.value)
                view.nav_scene.poke()

    def state(self) -> tuple[bool, float, float, object]:
        """(active, width HU, level HU, picked point) read together."""
        with self.lock:
            return self.active, self.width, self.level, self.picked

    def set_active(self, on: bool) -> None:
        self.h_main.value = bool(on)  # its callback does the rest

    def on_pick(self, p) -> None:
        """A click on a slice at LPS ``p`` (mm): what "Slice click" says."""
        view, session = self.view, self.view.session
        mode = self.h_click.value
        where = f"({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm"
        if mode == "centre slices here":
            with self.lock:
                self.picked = np.asarray(p, float)
            view.nav_scene.poke()
            view.say(True, f"Slices centred at {where}" + (" (the live tip wins while known)" if self.live else ""))
        elif mode == "set entry":
            view.run("Set entry", session.set_entry, p)
        elif mode == "set target":
            view.run("Set target", session.set_target, p)
        elif mode == "add fiducial":
            view.run("Add fiducial", session.add_fiducial, p)


def info_html(key: str, seq: int, width: float, level: float, source: str, text: str) -> str:
    return (f"<div class='mt-row' id='mt-nav-{key}' data-seq='{seq}' data-wl='{width:.0f}/{level:.0f}' "
            f"data-source='{source}'>{text}</div>")


def grid(n: int, aspect: float) -> tuple[int, int]:
    """(columns, rows) of ``n`` tiles for a canvas of ``aspect`` (width / height)."""
    cols = 3 if aspect >= 1.15 and n > 4 else (2 if n > 1 else 1)
    return cols, math.ceil(n / cols)


class NavigationScene:
    """The tiles in one tab's canvas and the worker that renders them (see the module doc)."""

    def __init__(self, view):
        self.view = view
        self.scene_lock = threading.RLock()  # held while the tiles are added / the scene is reset
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._request = None  # (snap, panel)
        self._shown = None  # (panel key) the scene holds tiles for, None: not in nav mode
        self._tiles: dict = {}  # name -> (handle, PlaneView, (x, y) centre)
        self._layout = None
        self._key = None
        self._hu_cache: dict = {}  # keyed on _vol_gen: slices of this volume only
        self._vol = None  # the volume sliced last (held: its identity, not a reusable id(), keys the cache)
        self._vol_gen = 0  # +1 per new volume object
        self._history: dict = {}  # name -> [(t sent, PlaneView, (x, y))], oldest first (clicks)
        self._note = None  # the info line's tip note last shown
        self._seq = 0
        self._thread = threading.Thread(target=self._loop, name=f"monotracker-nav-{view.client_id}", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ called by the view
    def post(self, snap, panel) -> None:
        """The newest snapshot while ``panel``'s navigation view is the main view."""
        with self._lock:
            self._request = (snap, panel)
        self._wake.set()

    def poke(self) -> None:
        self._wake.set()

    def leave(self) -> None:
        """The 3D view takes the canvas back: forget the tiles (the caller resets the scene
        holding ``scene_lock``)."""
        with self._lock:
            self._request = None
            self._shown = None
            self._tiles = {}
            self._layout = None
            self._key = None
            self._history = {}

    def close(self) -> None:
        self._stop.set()
        self._wake.set()

    def tiles(self) -> dict:
        """name -> (PlaneView, (x, y) tile centre): what is on screen now (tests, clicks)."""
        with self._lock:
            return {k: (v[1], v[2]) for k, v in self._tiles.items()}

    # ------------------------------------------------------------------ worker
    def _loop(self) -> None:
        period = 1.0 / NAV_MAX_HZ
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            if self._stop.is_set():
                return
            t0 = time.monotonic()
            try:
                self._render_once()
            except Exception:  # one tab's view; the log has the traceback
                log.exception("navigation render failed for client %s", self.view.client_id)
            self._stop.wait(max(0.0, period - (time.monotonic() - t0)))

    def _render_once(self) -> None:
        with self._lock:
            req = self._request
        if req is None:
            return
        snap, panel = req
        active, width, level, picked = panel.state()
        vol = self.view.session.volume()
        if not active:
            return
        if vol is None:
            with self._lock:
                said = self._key == "no-ct"
                self._key = "no-ct"
            if not said:
                panel.h_info.content = info_html(panel.key, self._seq, width, level, "", "No CT loaded: nothing to slice.")
            return
        gen = self._volume_gen(vol)
        lo, hi = volume_bounds_lps(vol)
        max_age = getattr(getattr(self.view.session, "config", None), "max_pose_age_s", None)
        max_age = nav.SessionConfig.max_pose_age_s if max_age is None else float(max_age)
        np_ = nav.nav_point(snap, (lo + hi) / 2, picked, live=panel.live, max_pose_age_s=max_age)
        e, t = snap.plan.entry_lps_mm, snap.plan.target_lps_mm
        views = nav.plane_views(np_.point, e, t)
        try:
            cam = self.view.client.camera
            aspect = float(cam.aspect) if cam.image_height else 1.5
        except Exception:  # noqa: BLE001 - no camera message from the browser yet
            aspect = 1.5
        cols, rows = grid(len(views), aspect)
        r2 = lambda a: None if a is None else tuple(np.round(np.asarray(a, float), 2))
        sug, sug_r = suggested_balls(snap, panel.key)
        key = (gen, panel.key, r2(np_.point), r2(np_.tip_axis), np_.source, r2(e), r2(t), width, level, cols,
               tuple((f.id, f.status, r2(f.centre_lps_mm)) for f in snap.fiducials),
               None if sug is None else (sug.round(2).tobytes(), sug_r))
        with self._lock:
            same = key == self._key and self._shown == panel.key
            note_changed = np_.note != self._note
            seq = self._seq
        if same:
            if note_changed:  # the images stand; only the line on why the tip is not followed changes
                self._note = np_.note
                panel.h_info.content = info_html(panel.key, seq, width, level, np_.source, describe(np_, e, t))
            return
        images = {}
        for name, v in views.items():
            hu = self._hu(vol, v)
            images[name] = nav.render_view(hu, v, width=width, level=level, entry=e, target=t, tip=np_.tip,
                                           tip_axis=np_.tip_axis, fiducials=snap.fiducials, suggested=sug,
                                           suggested_radius_mm=sug_r)
        with self.scene_lock:
            active, *_ = panel.state()
            if not active:
                return
            self._show(panel, views, images, cols, rows, aspect)
        with self._lock:
            self._key = key
            self._seq += 1
            seq = self._seq
        self._note = np_.note
        panel.h_info.content = info_html(panel.key, seq, width, level, np_.source, describe(np_, e, t))

    def _volume_gen(self, vol) -> int:
        """A number that changes whenever ``vol`` is not the volume sliced last (the reference is
        held, so a new CT can never pass for the old one by reusing its ``id``); a new volume
        empties the slice cache. Worker thread only."""
        if vol is not self._vol:
            self._vol = vol
            self._vol_gen += 1
            self._hu_cache.clear()
        return self._vol_gen

    def _hu(self, vol, v):
        k = (self._volume_gen(vol), v.name, tuple(np.round(v.centre_lps, 3)), tuple(np.round(v.u, 6)), tuple(np.round(v.v, 6)),
             v.pixel_mm, v.size)
        hu = self._hu_cache.get(k)
        if hu is None:
            if len(self._hu_cache) > 20:
                self._hu_cache.clear()
            hu = self._hu_cache[k] = nav.sample_plane(vol, v)
        return hu

    def _show(self, panel, views, images, cols, rows, aspect) -> None:
        """Put the images on the tiles (added, laid out and the camera aimed when the layout or
        the step changes). Caller holds ``scene_lock``."""
        scene = self.view.scene
        with self._lock:
            layout = (panel.key, tuple(views), cols)
            fresh = self._shown != panel.key or self._layout != layout
        if fresh:
            scene.reset()
            tiles = {}
            for i, name in enumerate(views):
                c, r = i % cols, i // cols
                xy = ((c - (cols - 1) / 2) * (TILE + GAP), (r - (rows - 1) / 2) * (TILE + GAP))
                h = scene.add_image(f"/nav/{name}", images[name], TILE, TILE, format="jpeg", jpeg_quality=85,
                                    position=(xy[0], xy[1], 0.0), cast_shadow=False, receive_shadow=False)
                self._bind_click(h, name, panel)
                tiles[name] = (h, views[name], xy)
            self._aim(cols, rows, aspect)
            with self._lock:
                self._tiles, self._shown, self._layout = tiles, panel.key, layout
                for name, (_h, v, xy) in tiles.items():
                    self._remember(name, v, xy)
            return
        with self._lock:
            tiles = dict(self._tiles)
        for name, (h, _old, xy) in tiles.items():
            h.image = images[name]
            with self._lock:
                self._tiles[name] = (h, views[name], xy)
                self._remember(name, views[name], xy)

    def _remember(self, name, v, xy, now: float | None = None) -> None:
        """Tile ``name`` was just sent with geometry ``v`` at ``xy``: keep the geometries a click
        arriving now or soon may have been made on (caller holds ``_lock``)."""
        now = time.monotonic() if now is None else now
        hist = self._history.get(name, []) + [(now, v, xy)]
        self._history[name] = hist[_window_start(hist, now):]

    def _aim(self, cols, rows, aspect) -> None:
        client = self.view.client
        try:
            fov = float(client.camera.fov) if client.camera.update_timestamp else math.radians(50)
        except Exception:  # noqa: BLE001
            fov = math.radians(50)
        half_w = cols * (TILE + GAP) / 2
        half_h = rows * (TILE + GAP) / 2
        dist = 1.06 * max(half_h, half_w / max(aspect, 0.1)) / math.tan(fov / 2)
        with client.atomic():
            client.camera.up_direction = (0.0, -1.0, 0.0)
            client.camera.position = (0.0, 0.0, -dist)
            client.camera.look_at = (0.0, 0.0, 0.0)

    def _bind_click(self, handle, name, panel) -> None:
        view = self.view

        @handle.on_click
        @view.safe("Slice click")
        def _(event) -> None:
            p, why = self.pick_checked(name, event.ray_origin, event.ray_direction)
            if p is None:
                view.say(False, f"Slice click: {why}")
                return
            panel.on_pick(p)

    def pick(self, name, ray_origin, ray_direction, now: float | None = None):
        """The LPS point (mm) under a click ray (world coordinates) on tile ``name``, or None
        (off the tile, or refused: :meth:`pick_checked`)."""
        return self.pick_checked(name, ray_origin, ray_direction, now)[0]

    def pick_checked(self, name, ray_origin, ray_direction, now: float | None = None):
        """``(LPS point mm, "")`` under a click ray (world coordinates) on tile ``name``, or
        ``(None, why)``: off the tile, or the tile's geometry changed within
        :data:`CLICK_SETTLE_S` so much that an image the click may have landed on (the browser
        may not have replaced it yet) puts another point under it than the newest one does."""
        with self._lock:
            tile = self._tiles.get(name)
            hist = list(self._history.get(name, ()))
        if tile is None:
            return None, "not on a slice"
        o, d = np.asarray(ray_origin, float), np.asarray(ray_direction, float)
        if abs(d[2]) < 1e-9:
            return None, "not on a slice"
        hit = o + (-o[2] / d[2]) * d
        _h, v, xy = tile
        col, row = _pixel(v, xy, hit)
        if not (-0.5 <= col <= v.size - 0.5 and -0.5 <= row <= v.size - 0.5):
            return None, "not on a slice"
        p = v.to_lps(col, row)
        now = time.monotonic() if now is None else now
        for _t, v_old, xy_old in hist[_window_start(hist, now):]:
            miss = float(np.linalg.norm(v_old.to_lps(*_pixel(v_old, xy_old, hit)) - p))
            if miss > CLICK_TOL_MM:
                return None, (f"ignored: the {nav.TITLES.get(name, name)} slice moved under the click "
                              f"({miss:.1f} mm); click again once it stands still")
        return p, ""

    def world_of(self, name, p_lps):
        """The canvas point (scene units) where LPS ``p_lps`` is drawn on tile ``name`` (tests)."""
        with self._lock:
            _h, v, xy = self._tiles[name]
        col, row = v.to_pixel(p_lps)[0]
        return np.array([xy[0] + ((col + 0.5) / v.size - 0.5) * TILE, xy[1] + ((row + 0.5) / v.size - 0.5) * TILE, 0.0])


def _window_start(hist, now: float) -> int:
    """Index of the oldest entry of ``hist`` ([(t sent, ...)], oldest first) a click at ``now``
    may have landed on: those sent within :data:`CLICK_SETTLE_S` and the one before them (on
    screen when the window opened)."""
    for i, h in enumerate(hist):
        if h[0] >= now - CLICK_SETTLE_S:
            return max(0, i - 1)
    return max(0, len(hist) - 1)


def _pixel(v, xy, hit) -> tuple[float, float]:
    """(col, row) of canvas point ``hit`` on a tile of geometry ``v`` centred at ``xy``; image col
    grows with +x, row with +y (viser draws images x right, y down)."""
    return (((hit[0] - xy[0]) / TILE + 0.5) * v.size - 0.5, ((hit[1] - xy[1]) / TILE + 0.5) * v.size - 0.5)


def describe(np_, entry, target) -> str:
    """One line: where the slices cut and, with a live tip, how far it is from the plan."""
    p = np_.point
    where = f"({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm LPS"
    what = {"tip": "the needle tip (live)", "target": "the planned target", "picked": "the picked point",
            "centre": "the volume centre"}[np_.source]
    line = f"Slices through {what} at {where}; radiological: patient left on the image right"
    if np_.source == "tip" and entry is not None and target is not None:
        e, t = np.asarray(entry, float), np.asarray(target, float)
        d = (t - e) / np.linalg.norm(t - e)
        depth = float((p - e) @ d)
        off = float(np.linalg.norm((p - e) - depth * d))
        line += f". Tip: {np.linalg.norm(t - p):.1f} mm to target, depth {depth:.1f} mm past entry, {off:.1f} mm off path"
    if getattr(np_, "note", ""):
        line += f". {html.escape(np_.note)}"  # the pose's reason goes into the info HTML
    return line
