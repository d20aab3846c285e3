"""Never a stale number: every live figure on the page (tip and angle error, speed, latency, FRE,
predicted TRE, residuals) with its age, or blanked with "stale since ..." once its source is not
trusted or older than its display limit.

Pure functions of an engine snapshot. A figure is *live* when its source is trusted now and
younger than :data:`STALE_AFTER_S`; otherwise its number is not shown at all (a greyed "-")
and the line says since when the last live value dates (wall clock) and why. The engine's own
trust verdict (``snap.pose.trusted``, which already includes the controller's 0.15 s freshness
limit) decides whether the arm moves; the display limit here only catches a source that stopped
updating (a stopped or frozen camera, a robot no longer commanded).

Each figure is one ``<span class='mt-fig' id='mt-fig-KEY' data-live='1|0'>`` (tests read
``data-live`` and ``data-age``).
"""

from __future__ import annotations

import html
import time
from dataclasses import dataclass

#: a figure older than this (s, session clock) is stale whatever its source says
STALE_AFTER_S = 1.0


@dataclass(frozen=True)
class Figure:
    """One figure as shown: ``live`` or not, its ``age_s`` (s, None when unknown), and when not
    live ``why`` (one line) and ``since_t`` (session clock s of the last live value, None if never)."""

    key: str
    text: str
    live: bool
    age_s: float | None = None
    why: str = ""
    since_t: float | None = None


def _clock(wall_of, t: float | None) -> str:
    if t is None or wall_of is None:
        return ""
    return time.strftime("%H:%M:%S", time.localtime(wall_of(t)))


def age_text(age_s: float) -> str:
    """"50 ms old" under a second, "2.3 s old" above."""
    return f"{1000 * age_s:.0f} ms old" if age_s < 1.0 else f"{age_s:.1f} s old"


def figure_html(fig: Figure, wall_of=None) -> str:
    """``fig`` as one span: the value and its age, or a greyed "-" with "stale since ...: why"."""
    age = "" if fig.age_s is None else f" data-age='{fig.age_s:.3f}'"
    if fig.live:
        small = "" if fig.age_s is None else f" <small class='mt-age'>{age_text(fig.age_s)}</small>"
        return f"<span class='mt-fig' id='mt-fig-{fig.key}' data-live='1'{age}><b>{fig.text}</b>{small}</span>"
    when = _clock(wall_of, fig.since_t)
    note = f"stale since {when}: {fig.why}" if when else f"not available: {fig.why}"
    return (f"<span class='mt-fig mt-stale' id='mt-fig-{fig.key}' data-live='0'{age}><b>-</b> "
            f"<small>{html.escape(note)}</small></span>")


def _fmt(v, unit: str, nd: int) -> str:
    return "-" if v is None else f"{v:.{nd}f}{unit}"


def pose_why(snap) -> str:
    """Why the pose's figures are not live now ("" when they are)."""
    pose = snap.pose
    cam = snap.camera
    if pose is None:
        return "camera stopped" if not cam.running else "no pose yet"
    if not cam.running:
        return "camera stopped"
    if not pose.trusted:
        return f"pose not trusted ({pose.reason})" if pose.reason else "pose not trusted"
    age = float(snap.t) - float(pose.t)
    if age > STALE_AFTER_S:
        return f"pose {age:.1f} s old"
    return ""


def pose_figures(snap) -> dict[str, Figure]:
    """FRE, predicted TRE and the registration latency of ``snap.pose``."""
    pose = snap.pose
    why = pose_why(snap)
    age = None if pose is None else max(0.0, float(snap.t) - float(pose.t))
    since = None if pose is None else pose.trusted_t
    out = {}
    for key, v, unit, nd in (("fre", None if pose is None else pose.fre_mm, " mm", 2),
                             ("tre", None if pose is None else pose.predicted_tre_mm, " mm", 2),
                             ("reglat", None if pose is None else pose.latency_ms, " ms", 0)):
        live = not why and v is not None
        out[key] = Figure(key, _fmt(v, unit, nd), live, age, why or "no value", since)
    return out


def robot_figures(snap) -> dict[str, Figure]:
    """Tip error, angle error (from the newest trusted pose), speed (the arm's own state) and
    capture -> command latency (of the newest command)."""
    r = snap.robot
    t = float(snap.t)
    # tip / angle error: the pose they come from must be trusted now, the arm connected, not stopped
    if r.state == "estopped":
        why = "robot e-stopped"
    elif not r.connected:
        why = "robot not connected"
    else:
        why = pose_why(snap)
    err_age = None if r.errors_t is None else max(0.0, t - float(r.errors_t))
    if not why and (err_age is None or r.tip_error_mm is None):
        why = "no trusted pose with a hand-eye and a path"
    if not why and err_age > STALE_AFTER_S:
        why = f"pose {err_age:.1f} s old"
    since = r.errors_t if r.errors_t is not None else (None if snap.pose is None else snap.pose.trusted_t)
    out = {
        "tip": Figure("tip", _fmt(r.tip_error_mm, " mm", 2), not why, err_age, why, since),
        "angle": Figure("angle", _fmt(r.angle_error_deg, "&deg;", 2), not why, err_age, why, since),
    }
    out["speed"] = (Figure("speed", _fmt(r.speed_mm_s, " mm/s", 1), True) if r.connected
                    else Figure("speed", "-", False, None, "robot not connected"))
    lat_age = None if r.command_t is None else max(0.0, t - float(r.command_t))
    if r.latency_ms is None or lat_age is None:
        lat_why = "no command yet"
    elif r.state != "tracking":
        lat_why = f"robot {r.state}: no commands"
    elif lat_age > STALE_AFTER_S:
        lat_why = f"no command for {lat_age:.1f} s"
    else:
        lat_why = ""
    out["latency"] = Figure("latency", _fmt(r.latency_ms, " ms", 0), not lat_why, lat_age, lat_why, r.command_t)
    return out


def residuals_live(snap) -> tuple[bool, str]:
    """Whether the per-fiducial residuals of ``snap.pose`` are live, and why not."""
    why = pose_why(snap)
    return not why, why
