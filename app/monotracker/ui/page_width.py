"""The width of a tab's page in CSS px, as the browser has it (the compact / wide layout switch).

viser 1.1.1 tells the server no CSS size of the page: its camera message carries the 3D canvas's
drawing buffer (``image_width`` = CSS width x an adaptive pixel ratio of 0.75 / 0.875 / 1 x the
screen's ``devicePixelRatio``), so on a HiDPI screen (ratio 2) a 1440 px wide page read as
~1780-2130 px and got the wide panels. Its pixel ratio can only be fixed by a ``?fixedDpr=`` in
the address the user types, and fixed at 1 it would also give up the ratio's drop on a slow
(software-rendered) browser.

Here the page reports its own width: :func:`install` sends the tab one small script (viser's
``RunJavascriptMessage``, the way viser itself loads plotly.js) that keeps ``window.innerWidth``
in the tab's ``localStorage`` under a key of this tab (:func:`storage_key`; ``localStorage`` is
shared by every tab of the origin), at once and on every resize; :class:`PageWidth` reads it
back through viser's ``LocalStorageHandle`` when the canvas's size changes (a resize sends a new
camera message, and the script's write comes before that read on the same connection).
"""

from __future__ import annotations

import logging
import threading

log = logging.getLogger(__name__)

#: how long one read of the stored width may wait for the browser (s); the layout keeps its
#: current choice meanwhile
READ_TIMEOUT_S = 5.0


def storage_key(client_id) -> str:
    """The ``localStorage`` key (viser adds its ``viser-user:`` prefix) of tab ``client_id``."""
    return f"mt-page-css-width-{client_id}"


def script(client_id) -> str:
    """The page script that keeps this tab's ``innerWidth`` (CSS px) under :func:`storage_key`."""
    key = "viser-user:" + storage_key(client_id)
    return ("(() => { const put = () => { try { localStorage.setItem(%r, String(window.innerWidth)); } "
            "catch (e) {} }; put(); window.addEventListener('resize', put); })();" % key)


def install(client) -> bool:
    """Send :func:`script` to ``client`` (a :class:`viser.ClientHandle`); False when this viser
    has no way to (then the width stays unknown and the layout compact)."""
    try:
        from viser import _messages

        client._websock_connection.queue_message(_messages.RunJavascriptMessage(source=script(client.client_id)))
        return True
    except Exception:  # another viser: no page width, the compact layout
        log.exception("could not install the page-width script")
        return False


class PageWidth:
    """The CSS width (px) of one tab's page: ``width`` (None until the page has reported it).
    :meth:`refresh` reads it again; called from viser's camera callback (its thread pool) when
    the canvas's drawing-buffer size changed, it never blocks the render thread."""

    def __init__(self, client):
        self.client = client
        self.width: float | None = None
        self._lock = threading.Lock()
        self._seen_buffer = None
        self.installed = install(client)
        if self.installed:
            client.camera.on_update(self._on_camera)

    def _on_camera(self, cam) -> None:
        size = (cam.image_width, cam.image_height)
        with self._lock:
            if size == self._seen_buffer:
                return  # the camera moved: the page's size did not change
            self._seen_buffer = size
        self.refresh()

    def refresh(self) -> float | None:
        """Read the stored width now (waits up to :data:`READ_TIMEOUT_S`); the new value or None."""
        try:
            raw = self.client.local_storage.get_item(storage_key(self.client.client_id), timeout=READ_TIMEOUT_S)
        except Exception:  # noqa: BLE001 - a tab gone, or a browser refusing localStorage: keep what we had
            return None
        try:
            w = float(raw) if raw is not None else None
        except ValueError:
            w = None
        if w is not None and w > 0:
            with self._lock:
                self.width = w
        return w
