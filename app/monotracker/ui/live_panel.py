"""The live camera + overlay in the main view (Register and Robot; issue 33 item 1).

The overlay decides whether the arm may move, so on the live steps it fills the main view: a
viser panel of this tab floated at the canvas's top-left corner (viser's ``float``), as wide as
the canvas between the status panel and the step panel (``view.MAIN_LIVE_PX``), the image at
the panel's width with its aspect kept. The 3D context (head, arm, path) stays visible below it
where the window is taller than the image, and the tick box **Live image in the main view** (in
the step panel, per tab) hides it to give the 3D view the whole area. CT and Plan never show it.
(A first version forced the panel's position and size with an ``!important`` stylesheet; the
browser test's clicks then hung, probably viser's layout observers fighting it.)
"""

from __future__ import annotations

import numpy as np

#: px of window chrome above and below the image inside the floating panel (header, caption)
CHROME_PX = 96
#: the steps that show the live image in the main view
MAIN_LIVE_STEPS = ("register", "robot")


def live_css(status_px: int, steps_px: int, aspect_w_over_h: float) -> str:
    """The stylesheet for the live image inside its floating panel: as wide as the panel,
    aspect kept. (A rule that also forced the panel's own position and width with !important
    froze Chromium's page: viser's layout observers fought it; the panel is placed with viser's
    own ``float`` instead.) ``status_px``, ``steps_px``, ``aspect_w_over_h`` are kept in the
    rule's comment so a layout change re-sends it."""
    a = max(0.5, min(4.0, float(aspect_w_over_h)))
    return (f"<style id='mt-live-css'>/* {int(status_px)} {int(steps_px)} {a:.4f} */ "
            f"[data-floating-window] #mt-live-main ~ * img, [data-floating-window] img {{ max-width: 100%; "
            f"height: auto; }}</style>")


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
        self._width: int | None = None

    def show_frame(self, jpeg) -> None:
        """Show one overlay frame already encoded as JPEG (the same bytes go to every tab; viser's
        image props are the encoded data and its format, so nothing is encoded again here)."""
        self.h_img._format = "jpeg"
        self.h_img._data = jpeg

    def update(self, step: str, wanted: bool, widths: tuple[int, int], image_size, live_px: int | None = None) -> None:
        """Show the panel on a live step when ``wanted``, ``live_px`` wide (the canvas between the
        panels, ``view.MAIN_LIVE_PX``) at the canvas's top left; keep its stylesheet true to the
        panel ``widths`` (status px, steps px) and the camera's ``image_size`` (w, h px or None)."""
        show = step in MAIN_LIVE_STEPS and wanted
        if live_px is not None and live_px != self._width:
            self._width = live_px
            self.panel.float(x=0, y=0, width=live_px)
        aspect = 16 / 9 if not image_size else image_size[0] / max(1, image_size[1])
        css = live_css(widths[0], widths[1], aspect)
        if css != self._css:
            self._css = css
            self.h_css.content = css
        if show != self._shown:
            self._shown = show
            self.panel.visible = show
