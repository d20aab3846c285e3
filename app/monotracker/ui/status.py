"""Always-visible status banner (HTML) and the page's stylesheet, built from an engine snapshot.

Pure functions: ``state_html(snap)`` shows the robot state in a big coloured block (DISARMED
grey, ARMED orange, TRACKING green, HOLDING amber, E-STOPPED red) and, hidden until the page
loses its server, "CONNECTION LOST - robot state unknown"; ``control_html`` who is in control;
``status_html(snap, ...)`` the active alarms (each with the time it began), the camera and pose
state, the workflow steps (done / current / to do) and the newest warning not already listed. ``CSS`` makes
buttons and text large enough for gloved hands on a touch screen and the stop button huge.
"""

from __future__ import annotations

import html
import time

#: docked panel widths (px) for a compact screen (1280x800: the canvas keeps 480-540 px between
#: the panels, enough for the 3D head or the navigation slices) and a wide one (>= 1700 px).
#: ``steps_live``: Calibrate (the live image in the step panel); ``steps_main_live``: Register and
#: Robot, where the live image is in the main view (``ui/live_panel.py``) and the step panel
#: holds only controls
PANEL_PX = {"status": 330, "steps": 440, "steps_live": 480, "steps_main_live": 400}
PANEL_PX_WIDE = {"status": 360, "steps": 470, "steps_live": 640, "steps_main_live": 470}
WIDE_PX = (1650, 1750)  # viewport widths (px) to switch to compact below / to wide above (hysteresis)


def fmt(v, unit="", nd=1) -> str:
    """A number with its unit, or '-' for None."""
    return "-" if v is None else f"{v:.{nd}f}{unit}"


STATE_STYLE = {
    "disarmed": ("#5f6b76", "DISARMED", "robot will not move"),
    "armed": ("#d9730d", "ARMED", "ready to track"),
    "tracking": ("#1f8f3a", "TRACKING", "robot follows the head"),
    "holding": ("#c99a06", "HOLDING", "robot holds still: pose not trusted"),
    "estopped": ("#c81e1e", "E-STOPPED", "reset the e-stop to continue"),
}

STEPS = (("ct", "1 CT"), ("plan", "2 Plan"), ("register", "3 Register"), ("robot", "4 Robot"))

LEVEL_COLOUR = {"alarm": "#c81e1e", "warning": "#b7791f", "info": "#2b6cb0"}

CSS = """
<style>
.mantine-Button-root { min-height: 3.1rem !important; font-size: 1.1rem !important; }
.mantine-Button-root[style*="red"] { min-height: 5.2rem !important; font-size: 1.9rem !important;
  font-weight: 800 !important; letter-spacing: 0.04em; }
.mantine-SegmentedControl-label, .mantine-Input-input, .mantine-TextInput-input { font-size: 1.05rem !important; }
.mt-status { font-family: system-ui, sans-serif; }
.mt-state { color: white; border-radius: 8px; padding: 8px 14px; margin-bottom: 6px; height: 4.9rem;
  overflow: hidden; box-sizing: border-box; }
.mt-conn-lost { display: none; }
/* viser dims the GUI and sets pointer-events:none on it while the websocket is down: then the
   robot state shown is stale, say so over it */
div[style*="pointer-events: none"] .mt-conn-lost { display: block; position: fixed; left: 0; right: 0; top: 0;
  z-index: 10000; background: #000; color: #ff4040; font: 800 2.2rem system-ui, sans-serif; text-align: center;
  padding: 18px; border-bottom: 6px solid #ff4040; }
div[style*="pointer-events: none"] .mt-state { filter: grayscale(1); }
/* the banner spans the page: the status panel's dock region above every other panel meanwhile */
[data-dock-region]:has(div[style*="pointer-events: none"] .mt-conn-lost) { z-index: 10001 !important; overflow: visible !important; }
/* STOP first: the status panel (robot state, STOP) stays above any modal (a PIN pad): its dock
   region over the modal's overlay (viser draws modals at z-index 100+), so a gloved press on STOP is
   never swallowed by an open pad (issue 34; tests/ui/test_stop_with_modal.py) */
[data-dock-region]:has(#mt-robot-state) { z-index: 1000 !important; }
.mt-control { border-radius: 6px; padding: 8px 12px; font-size: 1.15rem; font-weight: 700; margin: 4px 0; }
.mt-control.mine { background: #e6fffa; color: #234e52; border: 2px solid #38a169; }
.mt-control.viewing { background: #fffbea; color: #744210; border: 2px solid #d69e2e; }
.mt-alarms { list-style: none; padding: 0; margin: 4px 0; }
.mt-alarm { color: white; border-radius: 6px; padding: 6px 10px; font-size: 1.05rem; margin-bottom: 4px; }
.mt-alarm { overflow-wrap: anywhere; }
.mt-alarm .mt-since { display: block; font-weight: 400; font-size: 0.9rem; opacity: 0.9; }
.mt-alarm .mt-remedy { display: block; font-weight: 400; font-size: 0.9rem; }
.mt-pin-dots { font-size: 2.2rem; letter-spacing: 0.2em; text-align: center; min-height: 3rem; }
.mt-state b { display: block; font-size: 2.0rem; line-height: 1.15; letter-spacing: 0.05em; white-space: nowrap; }
.mt-state span { display: block; font-size: 0.95rem; line-height: 1.2; white-space: normal; overflow-wrap: anywhere; }
.mt-row { font-size: 1.05rem; margin: 3px 0; overflow-wrap: anywhere; }
.mt-wrap, .mt-status, .mt-msg, .mt-alert, .mt-banner-ok, .mt-banner-bad, .mt-control { overflow-wrap: anywhere;
  white-space: normal; max-width: 100%; box-sizing: border-box; }
.mt-fig small.mt-age { color: #777; font-weight: 400; }
.mt-stale, .mt-fig.mt-stale { color: #8a8a8a !important; }
.mt-fig.mt-stale small { font-style: italic; }
.mt-steps span { display: inline-block; padding: 4px 10px; margin-right: 4px; border-radius: 14px;
  background: #e2e8f0; color: #333; font-size: 1.0rem; }
.mt-steps span.done { background: #c6f6d5; color: #22543d; }
.mt-steps span.now { background: #2b6cb0; color: white; font-weight: 700; }
.mt-alert { color: white; border-radius: 6px; padding: 8px 12px; font-size: 1.1rem; margin-top: 6px; font-weight: 600; }
.mt-msg { border-radius: 6px; padding: 8px 12px; font-size: 1.1rem; font-weight: 600; }
.mt-msg.ok { background: #e6fffa; color: #234e52; border: 2px solid #38a169; }
.mt-msg.err { background: #fff5f5; color: #822727; border: 2px solid #e53e3e; }
.mt-banner-bad { background: #c81e1e; color: white; font-size: 1.25rem; font-weight: 700; padding: 8px 12px; border-radius: 6px; }
.mt-banner-ok { background: #1f8f3a; color: white; font-size: 1.15rem; font-weight: 600; padding: 8px 12px; border-radius: 6px; }
table.mt { border-collapse: collapse; font-size: 1.0rem; width: 100%; }
table.mt td, table.mt th { border-bottom: 1px solid #ddd; padding: 3px 6px; text-align: left; }
</style>
"""

_STEP_ORDER = [s for s, _ in STEPS]


def _esc(s) -> str:
    return html.escape(str(s))


def camera_line(snap) -> str:
    cam = snap.camera
    if cam.error:
        return f"Camera <b>{_esc(cam.source)}</b>: <b style='color:#c81e1e'>{_esc(cam.error)}</b>"
    if cam.running:
        return f"Camera <b>{_esc(cam.source)}</b>: running, {cam.fps:.0f} fps"
    return f"Camera <b>{_esc(cam.source)}</b>: stopped"


def averaged_note(pose) -> str:
    """", read from the mean of N still frames" when the detector read the opt-in still-view
    mean for ``pose`` (N > 1), else "": the team sees that the figures come from several frames."""
    n = int(getattr(pose, "averaged_frames", 1) or 1)
    return f", read from the mean of {n} still frames" if n > 1 else ""


def pose_line(snap) -> str:
    """The pose in one line: VALID with FRE and predicted TRE (each with its age), or why not
    (no figure shown: :mod:`monotracker.ui.freshness`)."""
    from monotracker.ui.freshness import figure_html, pose_figures, pose_why

    p = snap.pose
    if p is None:
        return "Pose: <b>none yet</b>" if snap.camera.running else "Pose: <b>none</b> (camera stopped)"
    f = pose_figures(snap)
    if f["fre"].live:
        return (f"Pose: <b style='color:#1f8f3a'>VALID</b>, FRE {figure_html(f['fre'])}, "
                f"predicted TRE {figure_html(f['tre'])}, {p.n_visible} fiducials{averaged_note(p)}")
    return f"Pose: <b style='color:#c81e1e'>NOT VALID</b>: {_esc(pose_why(snap))}"


def recent_alert(snap, now_wall: float | None = None, within_s: float = 6.0):
    """The newest warning/alarm raised in the last ``within_s`` seconds (wall clock), or None."""
    now_wall = time.time() if now_wall is None else now_wall
    for ev in reversed(snap.alerts):
        if ev.level in ("warning", "alarm") and now_wall - ev.t <= within_s:
            return ev
    return None


def state_html(snap) -> str:
    """The robot state in a big coloured block (fixed height: STOP below it never moves), and the
    connection-lost banner the stylesheet shows when the page loses the server."""
    colour, word, hint = STATE_STYLE.get(snap.robot.state, ("#333", snap.robot.state.upper(), ""))
    if not snap.robot.connected and snap.robot.state != "disarmed":
        hint = "robot NOT CONNECTED"
    return (f"<div class='mt-status'><div class='mt-conn-lost' id='mt-conn-lost'>CONNECTION LOST<br>"
            f"robot state unknown</div><div class='mt-state' id='mt-robot-state' "
            f"data-state='{_esc(snap.robot.state)}' style='background:{colour}'><b>{word}</b>"
            f"<span>{_esc(hint)}</span></div></div>")


def control_html(snap, client_id: str) -> str:
    """Who is in control, as this tab (``client_id``) sees it."""
    c = snap.control
    locked = (f"<div class='mt-row' style='color:#c81e1e'><b>PIN locked for {c.pin_locked_s:.0f} s</b> "
              f"after too many wrong tries</div>") if c.pin_locked_s > 0 else ""
    if c.controller == client_id:
        return (f"<div class='mt-control mine' id='mt-control' data-mine='1'>IN CONTROL: this station "
                f"({_esc(c.controller_label or client_id)})</div>{locked}")
    who = "nobody" if c.controller is None else (c.controller_label or c.controller)
    return (f"<div class='mt-control viewing' id='mt-control' data-mine='0'>VIEWING: {_esc(who)} is in control"
            f"<br><small>STOP works from every station</small></div>{locked}")


def alarms_html(snap, wall_of=None) -> str:
    """The active alarms, most important first, each with the time it began (``wall_of(since)``
    turns the session clock into wall time), until it clears."""
    alarms = tuple(getattr(snap, "alarms", ()) or ())
    if not alarms:
        return ""
    items = []
    for a in alarms:
        when = "" if wall_of is None else time.strftime("%H:%M:%S", time.localtime(wall_of(a.since)))
        count = f" (x{a.count})" if a.count > 1 else ""
        remedy = getattr(a, "remedy", "")
        todo = f"<span class='mt-remedy'>What to do: {_esc(remedy)}</span>" if remedy else ""
        items.append(f"<li class='mt-alarm' data-code='{_esc(a.code)}' data-level='{_esc(a.level)}' "
                     f"style='background:{LEVEL_COLOUR.get(a.level, '#555')}'>"
                     f"<b>{'ALARM' if a.level == 'alarm' else a.level.upper()}</b> {_esc(a.message)}"
                     f"{todo}<span class='mt-since'>since {when}{count}</span></li>")
    return f"<ul class='mt-alarms' id='mt-alarms'>{''.join(items)}</ul>"


def status_html(snap, *, view_step: str | None = None, notice: str | None = None, now_wall: float | None = None,
                wall_of=None) -> str:
    """Below STOP: active alarms, workflow steps, camera, pose, the newest warning."""
    parts = ["<div class='mt-status'>", alarms_html(snap, wall_of)]
    cur = _STEP_ORDER.index(snap.step) if snap.step in _STEP_ORDER else 0
    steps = []
    for i, (key, label) in enumerate(STEPS):
        cls = "done" if i < cur else ("now" if i == cur else "")
        mark = "&#10003; " if i < cur else ""
        shown = " &#9664;" if key == view_step else ""
        steps.append(f"<span class='{cls}'>{mark}{label}{shown}</span>")
    parts.append(f"<div class='mt-row mt-steps'>{''.join(steps)}</div>")
    parts.append(f"<div class='mt-row'>{camera_line(snap)}</div>")
    parts.append(f"<div class='mt-row'>{pose_line(snap)}</div>")
    if notice:
        parts.append(f"<div class='mt-row' style='color:#2b6cb0'><b>{_esc(notice)}</b></div>")
    active = {a.code for a in (getattr(snap, "alarms", ()) or ())}
    ev = recent_alert(snap, now_wall)
    if ev is not None and ev.code not in active:
        parts.append(f"<div class='mt-alert' id='mt-alert' data-code='{_esc(ev.code)}' "
                     f"style='background:{LEVEL_COLOUR[ev.level]}'>{'ALARM' if ev.level == 'alarm' else 'WARNING'}: "
                     f"{_esc(ev.message)}</div>")
    parts.append("</div>")
    return "".join(parts)


def message_html(ok: bool, text: str, seq: int = 0) -> str:
    """The result line of the operator's last command. ``seq`` counts the results shown in this
    page (``data-seq``), so a repeated identical result is still a new one (tests wait on it)."""
    cls = "ok" if ok else "err"
    mark = "&#10003;" if ok else "&#10007;"
    return (f"<div class='mt-msg {cls}' id='mt-msg' data-ok='{int(bool(ok))}' data-seq='{int(seq)}'>"
            f"{mark} {_esc(text)}</div>")
