"""Step 4 of one tab: Arm (operator PIN on the PIN pad), Disarm, Start / Stop tracking, Reset
e-stop; tip error, angle error, speed, latency and their live plot (last 60 s)."""

from __future__ import annotations

import time


from monotracker.ui import plots
from monotracker.ui import status as st
from monotracker.ui.navigation_panel import NavigationPanel
from monotracker.ui.pin_pad import PinPad
from monotracker.ui.freshness import figure_html, robot_figures


PLOT_PERIOD_S = 0.5


class RobotStep:
    def __init__(self, view):
        self.view = view
        self._plot_t = 0.0
        gui, session = view.gui, view.session
        self.folder = gui.add_folder("Step 4: robot")
        with self.folder:
            b_arm = gui.add_button("Arm (PIN)", color="orange", hint="the PIN set when the app was started")
            b_dis = gui.add_button("Disarm")
            b_start = gui.add_button("Start tracking", color="green")
            b_stop = gui.add_button("Stop tracking", color="yellow")
            b_reset = gui.add_button("Reset e-stop")
            self.h_info = gui.add_html("")
            gui.add_markdown("**Navigation view**: CT slices through the live needle tip (else the planned "
                             "target), probe's eye and along-path, in the main view")
            self.nav = NavigationPanel(view, "robot", live=True)
            self.h_plot = plots.add_tracking_plot(gui)

        @b_arm.on_click
        @view.safe("Arm")
        def _(_event) -> None:
            PinPad(view, "Arm the robot", lambda pin: view.run("Arm", session.arm, pin))

        for button, what, fn in ((b_dis, "Disarm", session.disarm), (b_start, "Start tracking", session.start_tracking),
                                 (b_stop, "Stop tracking", session.stop_tracking), (b_reset, "Reset e-stop", session.reset_estop)):
            self._bind(button, what, fn)

    def _bind(self, button, what: str, fn) -> None:
        view = self.view

        @button.on_click
        @view.safe(what)
        def _(_event) -> None:
            view.run(what, fn)

    def render(self, snap) -> None:
        self.h_info.content = robot_info_html(snap, lambda t: self.view.wall_time(snap, t))
        now = time.monotonic()
        if now - self._plot_t >= PLOT_PERIOD_S:  # the chart at 2 Hz: a redraw is costly in the browser
            self._plot_t = now
            plots.update_tracking_plot(self.h_plot, self.view.app.history())


def robot_info_html(snap, wall_of=None) -> str:
    """The robot's connection line and its live figures, each with its age or "stale since ..."
    (:mod:`monotracker.ui.freshness`): after an e-stop or with the pose not trusted no tip or
    angle error is shown as a number."""
    r = snap.robot
    conn = "connected" if r.connected else "<b style='color:#c81e1e'>NOT CONNECTED</b>"
    f = robot_figures(snap)
    rows = "".join(f"<div class='mt-row'>{name} {figure_html(f[key], wall_of)}</div>"
                   for name, key in (("Tip error", "tip"), ("Angle error", "angle"), ("Speed", "speed"),
                                     ("Latency", "latency")))
    return (f"<div class='mt-row mt-wrap'>Robot {conn}; {st._esc(r.message)}</div>"
            f"<div id='mt-robot-metrics'>{rows}</div>")
