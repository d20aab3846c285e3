"""Live plot of the robot's tip error (mm) and tip speed (mm/s) over the last minute (uPlot).

``add_tracking_plot(gui)`` adds the chart; ``update_tracking_plot(handle, history)`` redraws it
from ``history``: a list of ``(wall time s, tip error mm or None, speed mm/s)``. Time on the x
axis is seconds relative to now (negative = the past), so the right edge is always "now".
"""

from __future__ import annotations

import time

import numpy as np

WINDOW_S = 60.0


def _series():
    return (
        {"label": "t (s)"},
        {"label": "tip error (mm)", "stroke": "#c81e1e", "width": 2, "scale": "mm"},
        {"label": "speed (mm/s)", "stroke": "#2b6cb0", "width": 2, "scale": "mms"},
    )


def _axes():
    return (
        {"label": "seconds"},
        {"label": "tip error mm", "scale": "mm", "stroke": "#c81e1e"},
        {"label": "speed mm/s", "scale": "mms", "side": 1, "stroke": "#2b6cb0", "grid": {"show": False}},
    )


def history_arrays(history, now: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t relative to now s, tip error mm (NaN if none), speed mm/s) of the last ``WINDOW_S``."""
    now = time.time() if now is None else now
    rows = [(t - now, np.nan if e is None else float(e), float(v or 0.0)) for t, e, v in history if now - t <= WINDOW_S]
    if not rows:
        rows = [(0.0, np.nan, 0.0)]
    a = np.array(rows, dtype=float)
    return a[:, 0], a[:, 1], a[:, 2]


def add_tracking_plot(gui):
    t, e, v = history_arrays([])
    return gui.add_uplot(data=(t, e, v), series=_series(), axes=_axes(),
                         scales={"x": {"time": False}, "mm": {"auto": True}, "mms": {"auto": True}},
                         title="Tip error and speed", aspect=1.6)


def update_tracking_plot(handle, history) -> None:
    handle.data = history_arrays(history)
