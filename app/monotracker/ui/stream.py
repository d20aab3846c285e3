"""The live overlay stream: each camera frame is drawn, downscaled for display and JPEG-encoded
once, and the same bytes go to every tab that shows it (so 3 tabs cost one encode, not 3).

``encode_frame(image_bgr, estimate, snap)`` -> JPEG bytes (``display_width`` px wide, default 960,
aspect kept). With ``stream_code`` a 20-bit frame number is stamped into the bottom-left corner
of the *displayed* image (benchmark only; ``pushed`` maps it to the wall time it was encoded).
"""

from __future__ import annotations

import threading
import time

import cv2
import numpy as np

from monotracker.ui.overlay import draw_overlay, frame_code_strip


class OverlayStream:
    def __init__(self, *, display_width: int = 960, jpeg_quality: int = 80, stream_code: bool = False):
        self.display_width = int(display_width)
        self.jpeg_quality = int(jpeg_quality)
        self.stream_code = bool(stream_code)
        self.count = 0
        self.pushed: dict[int, float] = {}  # frame code -> wall time encoded (benchmark)
        self._lock = threading.Lock()

    def downscale(self, img: np.ndarray) -> np.ndarray:
        """``img`` at ``display_width`` px wide (never upscaled)."""
        h, w = img.shape[:2]
        if w <= self.display_width:
            return img
        return cv2.resize(img, (self.display_width, round(h * self.display_width / w)), interpolation=cv2.INTER_AREA)

    def encode_frame(self, image_bgr: np.ndarray, estimate, snap) -> bytes:
        """Downscale one BGR camera frame for display, draw the overlay on it at display size
        (marks and text crisp, a third of the pixels to copy and draw at 960 px), stamp
        (benchmark), encode JPEG once."""
        small = self.downscale(image_bgr)
        scale = small.shape[1] / image_bgr.shape[1]
        img = draw_overlay(small, estimate, snap, in_place=small is not image_bgr, px_scale=scale)
        return self.encode(img)

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
        return buf.tobytes()
