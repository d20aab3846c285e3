"""Learn the balls' colour from one click on a ball in the live camera image (issue 13).

viser 1.1 has no click events on GUI images (``GuiImageHandle`` has no ``on_click``), but scene
nodes do: ``ImageHandle.on_click`` gives the clicked ray (``ray_origin``, ``ray_direction``, world
coordinates). So "Learn ball colour" puts the newest camera frame into this tab's 3D view as an
image node facing the tab's own viewpoint (filling ~80 % of the view's height, between the
viewpoint and what it looks at), the operator clicks a ball on it, and the click's ray is
intersected with the image plane to give the pixel in the FULL-resolution frame, whatever size
the image is shown at (the picture sent to the browser is downscaled to at most
:data:`MAX_SEND_WIDTH` px). Then :meth:`Session.learn_ball_colour` learns the hue band on THE FRAME
SHOWN (kept with the pick), never on the camera's newest frame at click time, which may be seconds
later with the head moved (the pixel then on skin or drape): a session that takes the frame
(``frame=``, ``frame_index=``) learns from the shown image; one that takes only (x, y) is called
only while its newest frame is still the shown one, else the click is refused in one line. The
result (band, where it was saved) or the refusal is one line on this tab. A typed pixel
(``learn_at``) learns on the newest frame, without the 3D view.

Image node convention (viser's client, ``ThreeAssets.tsx``: a plane of ``render_width`` x
``render_height`` rotated by pi about x): in the node's frame the image lies in z = 0, centred
on the origin, columns along +x and rows along +y, the OpenCV camera convention that viser's
camera pose (``client.camera.wxyz``: +z looks forward, -y is up) uses too; so a node with the
camera's orientation shows the image upright.
"""

from __future__ import annotations

import threading

import numpy as np

#: the picture sent to the browser is at most this wide (px); clicks map to the full frame
MAX_SEND_WIDTH = 960
#: share of the view's height the picture fills
FILL = 0.8
NODE_NAME = "/mt_ball_colour_pick"


def _R(wxyz) -> np.ndarray:
    w, x, y, z = np.asarray(wxyz, float) / np.linalg.norm(wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def pick_placement(cam_position, cam_wxyz, look_at, fov_rad: float, aspect: float, image_wh):
    """Where to show a ``image_wh`` = (W, H) px picture in front of a viewer camera (position,
    OpenCV-convention orientation ``wxyz``, vertical field of view ``fov_rad``, canvas
    ``aspect`` = width / height): half-way to ``look_at`` (scene units), upright, filling
    :data:`FILL` of the view. Returns (position (3,), wxyz (4,), render_width, render_height)."""
    pos = np.asarray(cam_position, float)
    R = _R(cam_wxyz)
    dist = 0.5 * float(np.linalg.norm(np.asarray(look_at, float) - pos))
    if not np.isfinite(dist) or dist <= 1e-6:
        dist = 1.0
    view_h = 2.0 * dist * np.tan(0.5 * float(fov_rad))
    W, H = image_wh
    rh = FILL * view_h
    rw = rh * W / H
    if rw > FILL * view_h * float(aspect):                    # a narrow canvas: fit the width
        rw = FILL * view_h * float(aspect)
        rh = rw * H / W
    return pos + R[:, 2] * dist, np.asarray(cam_wxyz, float), float(rw), float(rh)


def click_to_pixel(ray_origin, ray_direction, position, wxyz, render_w: float, render_h: float, image_wh):
    """Pixel (x, y) of the full-resolution frame (``image_wh`` = (W, H) px, OpenCV pixel
    centres: pixel i covers [i - 0.5, i + 0.5]) where a click ray (world) meets the image node
    (``position``, ``wxyz``, ``render_w`` x ``render_h`` scene units); None off the picture."""
    R = _R(wxyz)
    o = R.T @ (np.asarray(ray_origin, float) - np.asarray(position, float))
    d = R.T @ np.asarray(ray_direction, float)
    if abs(d[2]) < 1e-12:
        return None
    t = -o[2] / d[2]
    if t < 0:
        return None
    hit = o + t * d
    W, H = image_wh
    u, v = hit[0] / render_w + 0.5, hit[1] / render_h + 0.5         # 0..1 across the picture
    if not (0.0 <= u <= 1.0 and 0.0 <= v <= 1.0):
        return None
    return float(u * W - 0.5), float(v * H - 0.5)


class BallColourPicker:
    """The pick mode of one tab. ``view`` gives ``scene`` (this tab's viser scene), ``client``
    (its ClientHandle: ``camera``), ``session`` and ``run(what, fn, *args)`` / ``say(ok, text)``;
    ``on_result(text)`` shows the outcome next to the button; ``on_end()`` is called when a click
    ends the pick (the page shows the live image over the main view again)."""

    def __init__(self, view, on_result=None, on_end=None):
        self.view = view
        self.on_result = on_result or (lambda text: None)
        self.on_end = on_end or (lambda: None)
        self._lock = threading.Lock()
        self._node = None
        self._placement = None
        self._size = None
        self._shown = None                       # (image BGR, frame_index) on the node

    @property
    def active(self) -> bool:
        with self._lock:
            return self._node is not None

    def start(self) -> bool:
        """Show the newest frame in the 3D view for a click; False (with one line) without one."""
        fr = self.view.session.latest_frame()
        if fr is None or fr[0] is None:
            self._tell(False, "no camera frame yet: start the camera, then click 'Learn ball colour'")
            return False
        img = np.asarray(fr[0])
        H, W = img.shape[:2]
        cam = self.view.client.camera
        pos, wxyz, rw, rh = pick_placement(cam.position, cam.wxyz, cam.look_at, cam.fov, cam.aspect, (W, H))
        send = img[:, :, ::-1]                                         # BGR -> RGB
        if W > MAX_SEND_WIDTH:
            import cv2

            send = cv2.resize(send, (MAX_SEND_WIDTH, int(round(H * MAX_SEND_WIDTH / W))), interpolation=cv2.INTER_AREA)
        self.cancel()
        node = self.view.scene.add_image(NODE_NAME, np.ascontiguousarray(send), rw, rh, format="jpeg",
                                         wxyz=wxyz, position=pos, cast_shadow=False, receive_shadow=False)
        with self._lock:
            self._node, self._placement, self._size = node, (pos, wxyz, rw, rh), (W, H)
            self._shown = (img, fr[1] if len(fr) > 1 else None)
        node.on_click(self._on_click)
        self._tell(True, f"click a ball in the camera image shown in the 3D view ({W}x{H} px frame); "
                         "'Cancel' to leave")
        return True

    def cancel(self) -> None:
        with self._lock:
            node, self._node, self._shown = self._node, None, None
        if node is not None:
            node.remove()

    def _on_click(self, event) -> None:
        with self._lock:
            if self._node is None:
                return
            pos, wxyz, rw, rh = self._placement
            size, shown = self._size, self._shown
        px = click_to_pixel(event.ray_origin, event.ray_direction, pos, wxyz, rw, rh, size)
        if px is None:
            self._tell(False, "that click is off the camera image: click a ball on it")
            return
        self.cancel()
        self.on_end()  # the live image over the main view comes back
        self._learn_on_shown(px[0], px[1], *shown)

    def _learn_on_shown(self, x_px: float, y_px: float, image, frame_index):
        """Learn at (x, y) of the frame that was shown (``image``, ``frame_index``), never of a
        newer one: the session learns from that image."""
        session = self.view.session
        fn = lambda x, y: session.learn_ball_colour(x, y, frame=image, frame_index=frame_index)
        return self._learn(fn, x_px, y_px)

    def learn_at(self, x_px: float, y_px: float):
        """Learn from pixel (x, y) of the camera's newest full-resolution frame (the typed pixel)."""
        return self._learn(self.view.session.learn_ball_colour, x_px, y_px)

    def _learn(self, fn, x_px: float, y_px: float):
        r = self.view.run("Ball colour", fn, float(x_px), float(y_px))
        if r is not None:
            self.on_result(f"{'' if r.ok else 'NOT LEARNED: '}{r.message} (at x {x_px:.0f}, y {y_px:.0f} px)")
        return r

    def _tell(self, ok: bool, text: str) -> None:
        self.view.say(ok, f"Ball colour: {text}")
        self.on_result(text)
