"""The live camera + overlay in the main view (Register and Robot; issue 33 item 1).

The overlay decides whether the arm may move, so on the live steps it fills the main view: a
viser panel of this tab floated over the 3D canvas, held by the page's stylesheet at the canvas's
top-left corner and as wide as the canvas between the status panel and the step panel (aspect
kept: never taller than the window). The 3D context (head, arm, path) stays visible below it
where the window is taller than the image, and the tick box **Live image in the main view** (in
the step panel, per tab) hides it to give the 3D view the whole area. CT and Plan never show it.

Why a stylesheet and not ``panel.float(width=...)`` alone: viser does not tell the server the
canvas's size in CSS px (its camera message carries the drawing buffer's size, scaled by an
adaptive pixel ratio); the server does know its own panel widths, so the rule
``left: <status px>; width: min(100% - <both panels>, (100vh - chrome) * aspect)`` keeps the
image as large as the window allows at any size, and follows a window resize without a message.
"""

from __future__ import annotations

import numpy as np

#: px of window chrome above and below the image inside the floating panel (header, caption)
CHROME_PX = 96
#: the steps that show the live image in the main view
MAIN_LIVE_STEPS = ("register", "robot")


def live_css(status_px: int, steps_px: int, aspect_w_over_h: float) -> str:
    """The stylesheet that places the live panel over the canvas (left edge at the status panel,
    as wide as the canvas or as the window's height allows at ``aspect_w_over_h``)."""
    a = max(0.5, min(4.0, float(aspect_w_over_h)))
    return (f"<style id='mt-live-css'>[data-floating-window]:has(#mt-live-main) {{ left: {int(status_px)}px !important; "
            f"top: 0 !important; width: min(calc(100% - {int(status_px) + int(steps_px)}px), "
            f"calc((100vh - {CHROME_PX}px) * {a:.4f})) !important; height: auto !important; }}"
            f"[data-floating-window]:has(#mt-live-main) img {{ width: 100% !important; height: auto !important; "
            f"max-height: none !important; object-fit: contain; }}</style>")


class LivePanel:
    """The floating live panel of one tab and its tick box."""

    def __init__(self, view):
        self.view = view
        gui = view.gui
        self.panel = gui.add_panel(visible=False)
        tab = self.panel.add_tab("Live camera + overlay")
        with tab:
            self.h_css = gui.add_html("")
            gui.add_html("<div id='mt-live-main' class='mt-row' style='font-size:0.9rem;color:#555'>"
                         "live camera with the registration overlay; the 3D view is below and behind "
                         "(untick <b>Live image in the main view</b> to see it whole)</div>")
            self.h_img = gui.add_image(np.zeros((54, 96, 3), np.uint8), format="jpeg")
        self.panel.float(x=0, y=0, width=640)
        self._shown: bool | None = None
        self._css: str = ""

    def show_frame(self, jpeg) -> None:
        """Show one overlay frame already encoded as JPEG (the same bytes go to every tab; viser's
        image props are the encoded data and its format, so nothing is encoded again here)."""
        self.h_img._format = "jpeg"
        self.h_img._data = jpeg

    def update(self, step: str, wanted: bool, widths: tuple[int, int], image_size) -> None:
        """Show the panel on a live step when ``wanted``; keep its stylesheet true to the panel
        ``widths`` (status px, steps px) and the camera's ``image_size`` (w, h px or None)."""
        show = step in MAIN_LIVE_STEPS and wanted
        aspect = 16 / 9 if not image_size else image_size[0] / max(1, image_size[1])
        css = live_css(widths[0], widths[1], aspect)
        if css != self._css:
            self._css = css
            self.h_css.content = css
        if show != self._shown:
            self._shown = show
            self.panel.visible = show
