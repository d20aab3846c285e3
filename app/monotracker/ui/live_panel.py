"""The live camera + overlay in the main view (Register and Robot; issue 33 item 1).

The overlay decides whether the arm may move, so on the live steps it fills the main view. The
image is a viser image of the tab's step panel (docked right, like the one it replaces), right
after a one-line caption (``#mt-live-main``); the page's stylesheet (:func:`live_css`) takes that
image out of the panel's flow (``position: fixed``) and places it over the canvas: its left edge
at the status panel, as wide as the canvas between the two docked panels, or as the window's
height allows with the camera's aspect kept. The 3D context (head, arm, path) stays visible
below it where the window is taller than the image, and the tick box **Live image in the main
view** (in the step panel, per tab) hides it to give the 3D view the whole area (no frame is
then encoded or sent to that tab). CT and Plan never show it.

Why the browser sizes it: viser does not tell the server the canvas's size in CSS px (its
camera message carries the drawing buffer's size, scaled by the screen's pixel ratio and an
adaptive one that drops to 0.75 on a slow machine; the page's CSS width comes later, from a
script of ours, ``ui/page_width.py``); the server knows its own panel widths. Why not a floating viser
panel: with the live image in one (``gui.add_panel().float()``, sized by viser's ``float`` or by
an ``!important`` rule, or only its image placed by this stylesheet) the page stopped drawing
frames once the stream began: the browser test's click on "3 Register" was done, then
Playwright's wait for two animation frames never ended (120 s). The image of a docked panel is
what the step panel had before, and the end-to-end test streamed into it.
"""

from __future__ import annotations

import numpy as np

#: px above the image (the canvas's top edge)
TOP_PX = 4
#: px left free below the image
BOTTOM_PX = 4
#: px kept between the image and each docked panel
GAP_PX = 2
#: px a docked region is wider than the panel width set (its resize handle: the status panel's
#: region measured 334 px for 330 at 1280x800 in the browser test)
DOCK_EDGE_PX = 4
#: the steps that show the live image in the main view
MAIN_LIVE_STEPS = ("register", "robot")
#: the image that follows this caption in the step panel is the one placed over the canvas
CAPTION = ("<div id='mt-live-main' class='mt-row' style='font-size:0.9rem;color:#555'>"
           "Live camera + overlay: in the main view (left)</div>")


def live_css(status_px: int, steps_px: int, aspect_w_over_h: float) -> str:
    """The stylesheet that places the live image over the canvas: left edge ``GAP_PX`` right of
    the status panel's region (``status_px`` + ``DOCK_EDGE_PX`` wide), ``TOP_PX`` below the canvas's top, as wide as the
    canvas between the docked panels (``steps_px``: the step panel) or as the window's height
    allows at ``aspect_w_over_h`` (w / h), whichever is smaller; aspect kept (CSS px)."""
    a = max(0.5, min(4.0, float(aspect_w_over_h)))
    left = int(status_px) + DOCK_EDGE_PX + GAP_PX
    side = int(status_px) + int(steps_px) + 2 * (DOCK_EDGE_PX + GAP_PX)
    return (f"<style id='mt-live-css'>div:has(> #mt-live-main) + div img {{ position: fixed; "
            f"left: {left}px; top: {TOP_PX}px; width: min(calc(100vw - {side}px), "
            f"calc((100vh - {TOP_PX + BOTTOM_PX}px) * {a:.4f})); max-width: none; height: auto; "
            f"z-index: 1; background: #000; }}</style>")


def shown_width(canvas_px: tuple[int, int] | None, aspect_w_over_h: float, fallback: int) -> int:
    """About the width (CSS px) :func:`live_css` gives the image on a canvas of ``canvas_px``
    (w, h, CSS px: the page's width less the docked panels, ``ui/page_width.py``), ``fallback``
    when not known: the width to encode the stream at."""
    if not canvas_px or canvas_px[0] <= 0 or canvas_px[1] <= 0:
        return int(fallback)
    a = max(0.5, min(4.0, float(aspect_w_over_h)))
    w, h = canvas_px
    return int(max(fallback, min(w - 2 * GAP_PX, (h - TOP_PX - BOTTOM_PX) * a)))


class LivePanel:
    """The live image of one tab (in its step panel, placed over the canvas) and its stylesheet."""

    def __init__(self, view):
        self.view = view
        gui = view.gui
        self.h_css = gui.add_html("")
        self.h_caption = gui.add_html(CAPTION, visible=False)
        self.h_img = gui.add_image(np.zeros((54, 96, 3), np.uint8), format="jpeg", visible=False)
        self._shown: bool | None = None
        self._css: str = ""

    def show_frame(self, jpeg) -> None:
        """Show one overlay frame already encoded as JPEG (the same bytes go to every tab; viser's
        image props are the encoded data and its format, so nothing is encoded again here)."""
        h = self.h_img
        if h._format != "jpeg":  # every prop assignment is a message to the browser
            h._format = "jpeg"
        h._data = jpeg

    def update(self, step: str, wanted: bool, widths: tuple[int, int], image_size) -> None:
        """Show the image on a live step when ``wanted``; keep its stylesheet true to the panel
        ``widths`` (status px, steps px) and the camera's ``image_size`` (w, h px or None)."""
        show = step in MAIN_LIVE_STEPS and wanted
        aspect = 16 / 9 if not image_size else image_size[0] / max(1, image_size[1])
        if show:
            css = live_css(widths[0], widths[1], aspect)
            if css != self._css:
                self._css = css
                self.h_css.content = css
        if show != self._shown:
            self._shown = show
            self.h_caption.visible = show
            self.h_img.visible = show
