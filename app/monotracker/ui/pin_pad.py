"""A PIN pad of big buttons in a modal window of one tab; the PIN is shown as dots only.

The digits are kept here, on the server, in this tab's pad only: the browser shows dots, no
other tab ever sees the pad, nothing is logged, and the digits are cleared after each try
(right or wrong) and when the pad is closed. ``on_pin(pin)`` gets the PIN (a viser worker
thread) and shows its own result line.
"""

from __future__ import annotations

import threading

ROWS = (("1", "2", "3"), ("4", "5", "6"), ("7", "8", "9"), ("Clear", "0", "OK"))
MAX_DIGITS = 12


def dots_html(n: int) -> str:
    """``n`` entered digits as dots (never the digits)."""
    shown = "&#9679; " * n if n else "<span style='color:#888'>enter the PIN</span>"
    return f"<div class='mt-pin-dots' id='mt-pin-dots' data-n='{int(n)}'>{shown}</div>"


class PinPad:
    """Open a PIN pad titled ``title`` on ``view``'s tab; ``on_pin(pin)`` is called on OK."""

    def __init__(self, view, title: str, on_pin):
        self.view = view
        self.on_pin = on_pin
        self._digits: list[str] = []
        self._lock = threading.Lock()
        gui = view.gui
        self.modal = gui.add_modal(title)
        with self.modal:
            self.h_dots = gui.add_html(dots_html(0))
            for row in ROWS:
                grp = gui.add_button_group("", list(row))

                @grp.on_click
                @view.safe(title)
                def _(event) -> None:
                    self._press(event.target.value)

            b_cancel = gui.add_button("Cancel")

            @b_cancel.on_click
            @view.safe(title)
            def _(_event) -> None:
                self._clear()
                self.modal.close()

    def _press(self, key: str) -> None:
        pin = None
        with self._lock:
            if key == "Clear":
                self._digits.clear()
            elif key == "OK":
                pin = "".join(self._digits)
                self._digits.clear()  # cleared after each try, right or wrong
            elif key.isdigit() and len(self._digits) < MAX_DIGITS:
                self._digits.append(key)
            n = len(self._digits)
        self.h_dots.content = dots_html(n)
        if pin is None:
            return
        if not pin:
            self.view.say(False, "PIN: press the digits first")
            return
        self.modal.close()
        self.on_pin(pin)

    def _clear(self) -> None:
        with self._lock:
            self._digits.clear()
