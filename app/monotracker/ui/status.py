"""Always-visible status banner (HTML) and the page's stylesheet, built from an engine snapshot.

Pure functions: ``status_html(snap, ...)`` shows the robot state in a big coloured block
(DISARMED grey, ARMED orange, TRACKING green, HOLDING amber, E-STOPPED red), the camera and pose
state, the workflow steps (done / current / to do) and the newest warning or alarm. ``CSS`` makes
buttons and text large enough for gloved hands on a touch screen and the stop button huge.
"""

from __future__ import annotations

import html
import time

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
.mt-state { color: white; border-radius: 8px; padding: 10px 14px; margin-bottom: 6px; }
.mt-state b { font-size: 2.0rem; letter-spacing: 0.05em; }
.mt-state span { font-size: 1.0rem; margin-left: 10px; }
.mt-row { font-size: 1.05rem; margin: 3px 0; }
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


def pose_line(snap) -> str:
    p = snap.pose
    if p is None:
        return "Pose: <b>none yet</b>"
    if p.trusted:
        fre = "-" if p.fre_mm is None else f"{p.fre_mm:.2f} mm"
        tre = "-" if p.predicted_tre_mm is None else f"{p.predicted_tre_mm:.2f} mm"
        return f"Pose: <b style='color:#1f8f3a'>VALID</b>, FRE {fre}, predicted TRE {tre}, {p.n_visible} fiducials"
    return f"Pose: <b style='color:#c81e1e'>NOT VALID</b>: {_esc(p.reason)}"


def recent_alert(snap, now_wall: float | None = None, within_s: float = 6.0):
    """The newest warning/alarm raised in the last ``within_s`` seconds (wall clock), or None."""
    now_wall = time.time() if now_wall is None else now_wall
    for ev in reversed(snap.alerts):
        if ev.level in ("warning", "alarm") and now_wall - ev.t <= within_s:
            return ev
    return None


def status_html(snap, *, view_step: str | None = None, notice: str | None = None, now_wall: float | None = None) -> str:
    """The banner shown at the top of the panel at all times."""
    colour, word, hint = STATE_STYLE.get(snap.robot.state, ("#333", snap.robot.state.upper(), ""))
    if not snap.robot.connected and snap.robot.state != "disarmed":
        hint = "robot NOT CONNECTED"
    parts = [f"<div class='mt-status'><div class='mt-state' id='mt-robot-state' data-state='{_esc(snap.robot.state)}' "
             f"style='background:{colour}'><b>{word}</b><span>{_esc(hint)}</span></div>"]
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
    ev = recent_alert(snap, now_wall)
    if ev is not None:
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
