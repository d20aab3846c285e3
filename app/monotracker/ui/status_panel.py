"""The always-visible status panel of one tab, docked left: who is in control, the robot state,
STOP, the active alarms and the result of this tab's last command.

Order (top to bottom) is fixed so STOP never moves: the robot-state block and STOP come first
and have a fixed height; everything that grows or shrinks (alarms, steps, camera, pose, the
result line) comes below STOP. STOP is also bound to the Space and Escape keys (viser command
hotkeys; they do not fire while the cursor is in a text field).

STOP first (``engine/pipeline_priority.py``): a press runs on viser's event-loop thread itself
(a coroutine callback, awaited as the message arrives, never queued behind the worker threads)
and only signals the robot's controller (``Session.request_estop``: shared memory and an event,
microseconds). The rest (waiting for the controller's acknowledgement, the audit row, this tab's
result line, redrawing every tab at once) follows on a worker thread. STOP stays on top of a
modal (the PIN pad): the status panel is drawn above the modal's overlay (``ui/status.py``
``CSS``), so a gloved press on STOP is never swallowed by an open pad.

"Take control" opens a PIN pad (:mod:`monotracker.ui.pin_pad`): the digits live on the server
in this tab's view only, the pad shows dots, the PIN is cleared after each try and never logged.
"""

from __future__ import annotations

import logging

from monotracker.ui import status as st
from monotracker.ui.pin_pad import PinPad
from monotracker.ui.status import PANEL_PX

log = logging.getLogger(__name__)


class StatusPanel:
    def __init__(self, view, snap):
        self.view = view
        gui = view.gui
        self.panel = gui.add_panel()
        tab = self.panel.add_tab("Status")
        with tab:
            self.h_state = gui.add_html(st.state_html(snap))
            self.h_stop = gui.add_button("STOP", color="red", hint="Emergency stop: the arm stops and stays stopped (keys: Space, Esc)")
            self.h_control = gui.add_html(st.control_html(snap, view.client_id))
            self.h_take = gui.add_button("Take control (PIN)", hint="make this station the one that drives the robot")
            self.h_status = gui.add_html(st.status_html(snap))
            self.h_msg = gui.add_html(st.message_html(True, ""))
            if getattr(view.app, "login", None) is not None:  # serve --allow-remote: the page login
                gui.add_html("<div class='mt-row'><a id='mt-logout' href='/logout'>Log out of this browser</a></div>")
        self.panel.dock_left()
        self.panel.set_width(PANEL_PX["status"])

        # the stop channel first, on the event loop (awaited before the worker-thread callback
        # below is even submitted); then the acknowledged stop, its audit row and the result line
        self.h_stop.on_click(self._stop_now)

        @self.h_stop.on_click
        @view.safe("STOP")
        def _(_event) -> None:
            self.stop()

        for key in ("space", "escape"):
            cmd = gui.add_command("STOP the robot", description="emergency stop (latched)", hotkey=key)
            cmd.on_trigger(self._stop_now)

            @cmd.on_trigger
            @view.safe("STOP")
            def _(_event) -> None:
                self.stop()

        @self.h_take.on_click
        @view.safe("Take control")
        def _(_event) -> None:
            PinPad(view, "Take control", self._claim)

    async def _stop_now(self, _event) -> None:
        """Runs on viser's event loop: signal the stop and return (never raises, never blocks)."""
        try:
            self.view.session.request_estop()
        except Exception:  # never into viser's message handler; stop() follows anyway
            log.exception("STOP signal failed")
        self.view.app.note_stop(self.view.client_id, self.view.label)

    def stop(self) -> None:
        """The acknowledged stop (worker thread): result line, and every tab redrawn at once."""
        self.view.run("STOP", self.view.session.estop)
        self.view.app.redraw_now()

    def _claim(self, pin: str) -> None:
        self.view.run("Take control", self.view.session.claim_control, self.view.client_id, pin, self.view.label)

    def render(self, snap, step: str) -> None:
        view = self.view
        self.h_state.content = st.state_html(snap)
        self.h_control.content = st.control_html(snap, view.client_id)
        self.h_take.visible = snap.control.controller != view.client_id
        self.h_status.content = st.status_html(snap, view_step=step, notice=view.notice,
                                               wall_of=lambda t: view.wall_time(snap, t))
