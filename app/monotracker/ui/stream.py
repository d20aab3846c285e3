"""The live overlay stream: each camera frame is drawn, downscaled for display and JPEG-encoded
once, and the same bytes go to every tab that shows it (so 3 tabs cost one encode, not 3).

``encode_frame(image_bgr, estimate, snap)`` -> JPEG bytes (``display_width`` px wide, default 960,
aspect kept). With ``stream_code`` (benchmark only) the frame number is written twice: a 20-bit
barcode stamped into the bottom-left corner of the *displayed* image, and a JPEG comment
(:func:`with_frame_comment`) the browser can read without decoding pixels; ``pushed`` maps it to
the wall time it was encoded.
"""

from __future__ import annotations

import threading
import time

import cv2
import numpy as np

from monotracker.ui.overlay import draw_camera_stopped, draw_overlay, frame_code_strip


#: the JPEG comment (COM segment) payload that carries a benchmark frame number
FRAME_COMMENT = b"MTFRAME "


def with_frame_comment(jpeg: bytes, index: int) -> bytes:
    """``jpeg`` with a COM segment ``MTFRAME <index>`` inserted right after its JFIF APP0 segment
    (or after SOI when there is none): the same image, decoders ignore comments."""
    payload = FRAME_COMMENT + str(int(index)).encode()
    seg = b"\xff\xfe" + (len(payload) + 2).to_bytes(2, "big") + payload
    at = 2
    if jpeg[2:4] == b"\xff\xe0":
        at = 4 + int.from_bytes(jpeg[4:6], "big")
    return jpeg[:at] + seg + jpeg[at:]


class OverlayStream:
    def __init__(self, *, display_width: int = 960, jpeg_quality: int = 80, stream_code: bool = False):
        self.display_width = int(display_width)
        self.jpeg_quality = int(jpeg_quality)
        self.stream_code = bool(stream_code)
        self.count = 0
        self.pushed: dict[int, float] = {}  # frame code -> wall time encoded (benchmark)
        self._lock = threading.Lock()

    def width_for(self, shown_px: int | None) -> int:
        """The width (px) to encode for a tab that shows the image ``shown_px`` CSS px wide:
        that width, at most ``display_width`` (None: ``display_width``). Pixels beyond what the
        tab shows only cost the server's encode and every browser's decode."""
        if shown_px is None or shown_px <= 0:
            return self.display_width
        return min(self.display_width, int(shown_px))

    def downscale(self, img: np.ndarray, width: int | None = None) -> np.ndarray:
        """``img`` at ``width`` (default ``display_width``) px wide (never upscaled)."""
        width = self.display_width if width is None else int(width)
        h, w = img.shape[:2]
        if w <= width:
            return img
        size = (width, round(h * width / w))
        k = w // width
        if k >= 2:
            if w % k or h % k:  # no whole factor: area averaging at the fractional ratio
                return cv2.resize(img, size, interpolation=cv2.INTER_AREA)
            # 2x and more: area averaging by the whole factor first (no aliasing, OpenCV's fast
            # path; INTER_AREA at a fractional ratio, 1280 -> 546 px, took 16 ms a frame)
            img = cv2.resize(img, (w // k, h // k), interpolation=cv2.INTER_AREA)
            if img.shape[1] == width:
                return img
        # the rest (under 2x) bilinear: it reads every source pixel anyway, at a fraction of the cost
        return cv2.resize(img, size, interpolation=cv2.INTER_LINEAR)

    def encode_frame(self, image_bgr: np.ndarray, estimate, snap, width: int | None = None) -> bytes:
        """Downscale one BGR camera frame for display (``width`` px, default ``display_width``),
        draw the overlay on it at that size (marks and text crisp, far fewer pixels to copy and
        draw), stamp (benchmark), encode JPEG once."""
        small = self.downscale(image_bgr, width)
        scale = small.shape[1] / image_bgr.shape[1]
        img = draw_overlay(small, estimate, snap, in_place=small is not image_bgr, px_scale=scale)
        return self.encode(img)

    def encode_stopped(self, image_bgr: np.ndarray | None, text: str, width: int | None = None,
                       aspect: float = 9 / 16) -> bytes:
        """The view of a camera that stopped: the last frame (or grey) at ``width`` px, dimmed,
        without overlay marks, with ``text`` across it; ``aspect`` (h/w) when there is no frame."""
        width = self.display_width if width is None else int(width)
        if image_bgr is not None:
            small = self.downscale(image_bgr, width)
            height = small.shape[0]
        else:
            small, height = None, int(round(width * aspect))
        return self.encode(draw_camera_stopped(small, small.shape[1] if small is not None else width, height, text))

    def encode(self, img_bgr: np.ndarray) -> bytes:
        """JPEG bytes of a display-size BGR image (frame code stamped when ``stream_code``)."""
        with self._lock:
            self.count += 1
            n = self.count
        if self.stream_code:
            img_bgr = img_bgr.copy()
            strip = frame_code_strip(n)
            img_bgr[-strip.shape[0]:, :strip.shape[1]] = strip
        ok, buf = cv2.imencode(".jpg", img_bgr, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        if self.stream_code:
            self.pushed[n] = time.time()
            return with_frame_comment(buf.tobytes(), n)
        return buf.tobytes()
