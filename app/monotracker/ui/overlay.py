"""The registration overlay drawn on the live camera image (BGR uint8, pixels).

What the operator sees on each frame (nothing here decides anything; it draws what the engine's
pose estimate says):

* each ball's state by colour *and* shape (:data:`BALL_STYLE`): seen = filled green dot (the
  detection) in a cyan ring (the CT fiducial reprojected with the estimated ``T_cam_ct``,
  ``cv2.projectPoints`` with the calibration ``K``, ``dist``); predicted (only the reprojection
  is known) = hollow cyan diamond; lost (``occluded`` / ``newly_lost``) = red ring with a cross;
  excluded as moved = orange square; set aside for this frame (found, but the other balls put it
  more than a pixel or two away: partly hidden, a reflection; ``set_aside``) = yellow triangle
  at the detection, the cyan ring where the others put it;
* one label per ball (its number and residual px, or its state), placed by
  :func:`place_labels` so that no two labels, no label and ball, no label and banner overlap; a
  label that finds no room beside its ball goes to a legend column with a leader line;
* text sized for the width the page shows the image at (:func:`text_scale`);
* the planned path projected (entry cyan cross -> target magenta);
* a banner along the top: green with FRE / predicted TRE / fiducials seen when the pose is
  valid, red with the reason when it is not; wrapped onto a second line or shrunk, never cut.

:func:`draw_camera_stopped`: the view of a camera that stopped (the last frame dimmed, the words).
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import cv2
import numpy as np

from monotracker.geometry import apply_transform
from monotracker.registration.projection import project_pixels

GREEN = (60, 200, 60)
CYAN = (255, 220, 0)
RED = (40, 40, 235)
MAGENTA = (255, 0, 255)
WHITE = (255, 255, 255)



def project_points(points_ct: np.ndarray, T_cam_ct: np.ndarray, K: np.ndarray, dist=None) -> np.ndarray:
    """CT points (n, 3) mm -> pixels (n, 2) through ``T_cam_ct`` and the camera model (the
    registration's projection, full OpenCV distortion model). Points behind the camera come
    back as NaN."""
    p_cam = apply_transform(T_cam_ct, np.atleast_2d(np.asarray(points_ct, float)))
    if len(p_cam) == 0:
        return np.zeros((0, 2))
    uv = np.full((len(p_cam), 2), np.nan)
    front = p_cam[:, 2] > 0
    if front.any():
        uv[front] = project_pixels(p_cam[front], np.asarray(K, float), dist)
    return uv


def _finite(p) -> bool:
    return p is not None and bool(np.all(np.isfinite(p)))


def _ipt(p) -> tuple[int, int]:
    return int(round(float(p[0]))), int(round(float(p[1])))


ORANGE = (0, 140, 255)
YELLOW = (0, 230, 255)
GREY = (160, 160, 160)

#: how each ball's state is drawn: (colour, shape, word). Shapes differ as well as colours (a
#: colour-blind reader, a washed-out screen): seen = filled dot in a ring, predicted = hollow
#: diamond, lost = ring with a cross, moved (excluded) = square, set aside for this frame =
#: triangle (in the ring where the other balls put it).
BALL_STYLE = {
    "seen": (GREEN, "dot", "seen"),
    "predicted": (CYAN, "diamond", "predicted"),
    "lost": (RED, "cross", "lost"),
    "moved": (ORANGE, "square", "moved: excluded"),
    "aside": (YELLOW, "triangle", "set aside"),
}


def ball_state(status: str, detected: bool, set_aside: bool = False) -> str:
    """A fiducial's estimate status, whether the frame has its detection and whether the
    estimate set it aside -> "seen" | "aside" (found, left out of this frame's pose) |
    "predicted" (only its reprojection is known) | "lost" (occluded, newly lost) | "moved"."""
    if status == "moved":
        return "moved"
    if status in ("occluded", "newly_lost"):
        return "lost"
    if status == "seen" and detected:
        return "aside" if set_aside else "seen"
    return "predicted"


FONT = cv2.FONT_HERSHEY_SIMPLEX


def text_scale(width_px: int) -> float:
    """Font scale for an image shown ``width_px`` wide: the image is encoded at the width the page
    shows it, so text keeps about the same on-screen size (11-16 px tall) at 480 px as at 1920."""
    return float(np.clip(width_px / 1280.0 * 0.75, 0.42, 0.75))


#: rendered texts kept for reuse (the banner and most labels repeat frame after frame): at most
#: this many (a few hundred kB)
SPRITE_CACHE = 256
_sprites: OrderedDict = OrderedDict()
_sprites_lock = threading.Lock()


def _sprite(s: str, scale: float, thick: int):
    """``s`` rendered once as two coverage masks (float32 0..1): its black outline (``thick`` + 3)
    and its fill (``thick``), anti-aliased, with the text origin (x, y) px inside the patch."""
    key = (s, round(float(scale), 4), int(thick))
    with _sprites_lock:
        sp = _sprites.get(key)
        if sp is not None:
            _sprites.move_to_end(key)
            return sp
    (tw, th), base = cv2.getTextSize(s, FONT, scale, thick + 3)
    pad = thick + 4
    outline = np.zeros((th + base + 2 * pad, tw + 2 * pad), np.uint8)
    fill = np.zeros_like(outline)
    org = (pad, pad + th)
    cv2.putText(outline, s, org, FONT, scale, 255, thick + 3, cv2.LINE_AA)
    cv2.putText(fill, s, org, FONT, scale, 255, thick, cv2.LINE_AA)
    sp = (outline.astype(np.float32)[..., None] / 255.0, fill.astype(np.float32)[..., None] / 255.0, org)
    with _sprites_lock:
        _sprites[key] = sp
        while len(_sprites) > SPRITE_CACHE:
            _sprites.popitem(last=False)
    return sp


def _text(img, s, org, colour, scale=0.7, thick=2):
    """``s`` at ``org`` (x, y px: the baseline's left end, as ``cv2.putText``) in ``colour`` with a
    black outline: drawn from :func:`_sprite` (the same pixels as two anti-aliased ``putText``
    calls, outline then fill, at a fraction of the cost when the text repeats)."""
    a_out, a_fill, (ox, oy) = _sprite(s, scale, thick)
    h, w = img.shape[:2]
    x0, y0 = int(org[0]) - ox, int(org[1]) - oy
    x1, y1 = x0 + a_out.shape[1], y0 + a_out.shape[0]
    cx0, cy0, cx1, cy1 = max(0, x0), max(0, y0), min(w, x1), min(h, y1)
    if cx0 >= cx1 or cy0 >= cy1:
        return
    ao = a_out[cy0 - y0:cy1 - y0, cx0 - x0:cx1 - x0]
    af = a_fill[cy0 - y0:cy1 - y0, cx0 - x0:cx1 - x0]
    region = img[cy0:cy1, cx0:cx1]
    out = region.astype(np.float32) * (1.0 - ao)
    out = out * (1.0 - af) + np.asarray(colour, np.float32) * af
    region[:] = (out + 0.5).astype(np.uint8)


def _text_box(s: str, scale: float, thick: int) -> tuple[int, int]:
    """(width, height) px of ``s`` drawn with :func:`_text` (outline included)."""
    (tw, th), base = cv2.getTextSize(s, FONT, scale, thick + 3)
    return tw + 2, th + base + 2


def _intersects(a, b) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def place_labels(anchors, sizes, width: int, height: int, avoid=(), gap: float = 10.0) -> list[tuple]:
    """Boxes (x0, y0, x1, y1) px for labels of ``sizes`` (w, h) next to ``anchors`` (x, y),
    no two intersecting and none intersecting ``avoid`` (boxes), inside the image.

    Each label tries 8 positions around its anchor at growing distances (gap, 2 gap, ... ); a
    label that finds no free place goes to a legend column down the right edge (the caller draws
    a leader line from the ball to any label not beside it). Greedy in the given order."""
    placed: list[tuple] = list(avoid)
    out = []
    for (ax, ay), (lw, lh) in zip(anchors, sizes):
        box = None
        if np.isfinite(ax) and np.isfinite(ay):
            for k in (1, 2, 3, 4, 6):
                d = gap * k
                for dx, dy in ((d, -lh / 2), (-d - lw, -lh / 2), (d, -d - lh), (d, d), (-d - lw, -d - lh),
                               (-d - lw, d), (-lw / 2, -d - lh), (-lw / 2, d)):
                    b = (ax + dx, ay + dy, ax + dx + lw, ay + dy + lh)
                    if b[0] < 0 or b[1] < 0 or b[2] > width or b[3] > height:
                        continue
                    if any(_intersects(b, p) for p in placed):
                        continue
                    box = b
                    break
                if box is not None:
                    break
        if box is None:  # the legend column: from the bottom right corner upwards
            x1 = width - 2
            y1 = height - 2
            while True:
                b = (x1 - lw, y1 - lh, x1, y1)
                if b[1] < 0:
                    b = (x1 - lw, 0, x1, lh)  # no room left at all: accept (a tiny image)
                    break
                if not any(_intersects(b, p) for p in placed):
                    break
                y1 -= 2
            box = b
        box = tuple(int(round(v)) for v in box)
        placed.append(box)
        out.append(box)
    return out


def _draw_ball(img, p, state: str, ring: int, thick: int) -> None:
    colour, shape, _ = BALL_STYLE[state]
    c = _ipt(p)
    if shape == "dot":
        cv2.circle(img, c, max(3, ring // 3), colour, -1, cv2.LINE_AA)
    elif shape == "diamond":
        pts = np.array([[c[0], c[1] - ring], [c[0] + ring, c[1]], [c[0], c[1] + ring], [c[0] - ring, c[1]]], np.int32)
        cv2.polylines(img, [pts], True, colour, thick, cv2.LINE_AA)
    elif shape == "triangle":
        h = ring * 0.87
        pts = np.array([[c[0], c[1] - ring], [c[0] + h, c[1] + ring / 2], [c[0] - h, c[1] + ring / 2]], np.int32)
        cv2.polylines(img, [pts], True, colour, thick + 1, cv2.LINE_AA)
    elif shape == "cross":
        cv2.circle(img, c, ring, colour, thick + 1, cv2.LINE_AA)
        r = int(ring * 0.7)
        cv2.line(img, (c[0] - r, c[1] - r), (c[0] + r, c[1] + r), colour, thick, cv2.LINE_AA)
        cv2.line(img, (c[0] - r, c[1] + r), (c[0] + r, c[1] - r), colour, thick, cv2.LINE_AA)
    else:
        cv2.rectangle(img, (c[0] - ring, c[1] - ring), (c[0] + ring, c[1] + ring), colour, thick + 1, cv2.LINE_AA)


def wrap_banner(msg: str, width: int, scale: float, thick: int, max_lines: int = 2) -> tuple[list[str], float]:
    """Lines of ``msg`` fitting ``width`` px at the largest scale <= ``scale`` with at most
    ``max_lines`` lines (the banner is never cut: the scale shrinks instead)."""
    words = msg.split()
    while True:
        lines, cur = [], ""
        for w in words:
            trial = f"{cur} {w}".strip()
            if cur and _text_box(trial, scale, thick)[0] > width:
                lines.append(cur)
                cur = w
            else:
                cur = trial
        if cur:
            lines.append(cur)
        fits = all(_text_box(ln, scale, thick)[0] <= width for ln in lines)
        if (len(lines) <= max_lines and fits) or scale <= 0.3:
            return lines, scale
        scale *= 0.9


def draw_overlay(image: np.ndarray, estimate, snap, *, in_place: bool = False, px_scale: float = 1.0,
                 label_boxes: list | None = None) -> np.ndarray:
    """Draw the overlay for one frame. ``estimate``: vision's ``PoseEstimate`` for this frame
    (or None); ``snap``: the engine snapshot (fiducial ids, positions, plan, camera model,
    engine's trust verdict). ``px_scale``: display px per camera px when ``image`` is the frame
    already downscaled for display (camera-pixel positions are scaled; marks and text are sized
    for the image drawn on, which is shown at its own width). ``label_boxes``: a list that gets
    the banner's and every label's box (x0, y0, x1, y1) px (tests). Returns the BGR image (a copy
    unless ``in_place``)."""
    img = image if in_place else image.copy()
    h, w = img.shape[:2]
    pose = snap.pose
    cam = snap.camera
    ids = list(pose.fiducial_status.keys()) if pose is not None else []
    by_id = {f.id: f for f in snap.fiducials}
    T = None
    if estimate is not None and getattr(estimate, "T_cam_ct", None) is not None:
        T = np.asarray(estimate.T_cam_ct, float)
    elif pose is not None and pose.T_cam_ct is not None:
        T = np.asarray(pose.T_cam_ct, float)
    status = list(getattr(estimate, "status", []) or [])
    if estimate is not None and len(status) == len(ids):
        status_by_id = dict(zip(ids, status))
    else:
        status_by_id = dict(pose.fiducial_status) if pose is not None else {}
    # vision's PoseEstimate: arrays in fiducial order; the engine's PoseSample ("sim-points"):
    # dicts keyed by fiducial id and no image points
    img_pts = np.asarray(getattr(estimate, "image_points_px", np.zeros((0, 2))), float).reshape(-1, 2) * px_scale
    res_raw = getattr(estimate, "residuals_px", None)
    if isinstance(res_raw, dict):
        residuals = np.array([res_raw.get(i, np.nan) for i in ids], float)
    elif res_raw is None:
        residuals = np.array([(pose.residuals_px.get(i, np.nan) if pose is not None else np.nan) for i in ids], float)
    else:
        residuals = np.asarray(res_raw, float).ravel()
    scale = max(0.5, w / 1280.0)  # marks (rings, lines) follow the image
    ts = text_scale(w)            # text keeps a legible on-screen size
    tthick = 1 if ts < 0.6 else 2

    proj = {}
    if T is not None and cam.K is not None and ids:
        centres = np.array([by_id[i].centre_lps_mm for i in ids if i in by_id])
        known = [i for i in ids if i in by_id]
        if len(known):
            uv = project_points(centres, T, cam.K, cam.dist) * px_scale
            proj = dict(zip(known, uv))
        plan = snap.plan
        if plan.entry_lps_mm is not None and plan.target_lps_mm is not None:
            e, t = project_points(np.array([plan.entry_lps_mm, plan.target_lps_mm]), T, cam.K, cam.dist) * px_scale
            if _finite(e) and _finite(t):
                cv2.line(img, _ipt(e), _ipt(t), MAGENTA, max(1, int(2 * scale)), cv2.LINE_AA)
                cv2.drawMarker(img, _ipt(e), CYAN, cv2.MARKER_CROSS, int(24 * scale), max(1, int(2 * scale)))
                cv2.drawMarker(img, _ipt(t), MAGENTA, cv2.MARKER_TILTED_CROSS, int(20 * scale), max(1, int(2 * scale)))

    # balls the estimate left out of its pose: fiducial id -> px from where the others put it
    aside = dict(getattr(pose, "set_aside", None) or {}) if pose is not None else {}
    if estimate is not None and getattr(estimate, "set_aside", None) is not None:
        aside = {ids[j]: px for j, px in estimate.set_aside if 0 <= j < len(ids)} \
            if not isinstance(estimate.set_aside, dict) else dict(estimate.set_aside)
    # the banner first: its height is reserved, labels never go under it
    trusted = pose is not None and pose.trusted
    valid = trusted and T is not None
    if valid:
        n_seen = sum(1 for s in status_by_id.values() if s == "seen")
        fre = f"{pose.fre_mm:.2f} mm" if pose.fre_mm is not None else "-"
        tre = f"{pose.predicted_tre_mm:.2f} mm" if pose.predicted_tre_mm is not None else "-"
        n_aside = sum(1 for i in aside if status_by_id.get(i) == "seen")
        msg = f"POSE OK   FRE {fre}   predicted TRE {tre}   fiducials {n_seen - n_aside}/{len(ids)}"
        if n_aside:
            msg += f" ({n_aside} more set aside)"
    elif pose is None:
        msg = "NO POSE YET: waiting for the first registration"
    else:
        msg = f"POSE NOT VALID: {pose.reason}"
        if pose.predicted_tre_mm is not None and "predicted error" not in pose.reason:
            msg += f"   (predicted TRE {pose.predicted_tre_mm:.2f} mm)"
    bscale = float(np.clip(w / 1280.0 * 0.95, 0.55, 0.95))
    bthick = 1 if bscale < 0.7 else 2
    pad = max(6, int(8 * scale))
    lines, bscale = wrap_banner(msg, w - 2 * pad, bscale, bthick)
    line_h = _text_box("Ag", bscale, bthick)[1] + 2
    bh = pad + line_h * len(lines) + pad // 2
    colour = (40, 120, 40) if valid else (30, 30, 190)
    cv2.rectangle(img, (0, 0), (w, bh), colour, -1)
    for k, ln in enumerate(lines):
        _text(img, ln, (pad, pad + line_h * (k + 1) - line_h // 4), WHITE, bscale, bthick)
    banner = (0, 0, w, bh)

    ring = max(6, int(14 * scale))
    thick = max(1, int(2 * scale))
    anchors, texts, colours = [], [], []
    for j, fid in enumerate(ids):
        stt = status_by_id.get(fid, "unknown")
        p_img = img_pts[j] if j < len(img_pts) else None
        p_proj = proj.get(fid)
        # no image points at all (the engine's PoseSample): a seen ball is drawn at its reprojection
        state = ball_state(stt, _finite(p_img) or (len(img_pts) == 0 and _finite(p_proj)), fid in aside)
        at = p_img if state in ("seen", "aside") and _finite(p_img) else p_proj
        if not _finite(at):
            continue
        if state in ("seen", "aside") and _finite(p_proj):
            cv2.circle(img, _ipt(p_proj), ring, CYAN, thick, cv2.LINE_AA)
        _draw_ball(img, at, state, ring, thick)
        r = residuals[j] if j < len(residuals) else np.nan
        if state == "seen":
            label = f"{fid} {r:.2f} px" if np.isfinite(r) else str(fid)
        elif state == "aside":
            label = f"{fid} set aside {aside[fid]:.1f} px"
        else:
            label = f"{fid} {BALL_STYLE[state][2]}"
        anchors.append((float(at[0]), float(at[1])))
        texts.append(label)
        colours.append(WHITE if state == "seen" else BALL_STYLE[state][0])
    sizes = [_text_box(t, ts, tthick) for t in texts]
    # every ball's own mark is kept clear too, so no label covers a ball
    marks = [(ax - ring, ay - ring, ax + ring, ay + ring) for ax, ay in anchors]
    boxes = place_labels(anchors, sizes, w, h, avoid=[banner] + marks, gap=ring + 3)
    for (ax, ay), box, text, col in zip(anchors, boxes, texts, colours):
        cx = min(max(ax, box[0]), box[2])
        cy = min(max(ay, box[1]), box[3])
        if np.hypot(cx - ax, cy - ay) > 2.5 * ring:  # far from its ball: a leader line
            cv2.line(img, (int(ax), int(ay)), (int(cx), int(cy)), col, 1, cv2.LINE_AA)
        _text(img, text, (box[0] + 1, box[3] - _text_box(text, ts, tthick)[1] // 4 - 1), col, ts, tthick)
    if label_boxes is not None:
        label_boxes.append(banner)
        label_boxes.extend(boxes)
    return img


def draw_camera_stopped(image: np.ndarray | None, width: int, height: int, text: str) -> np.ndarray:
    """The live view of a camera that does not deliver: the last frame (if any, ``width`` x
    ``height`` px) dimmed, no overlay marks, and ``text`` ("CAMERA STOPPED ...") across it."""
    if image is None or image.shape[1] != width:
        img = np.full((height, width, 3), 40, np.uint8)
    else:
        img = (image.astype(np.uint16) * 2 // 7).astype(np.uint8)
    ts = float(np.clip(width / 1280.0 * 1.4, 0.7, 1.4))
    th = 2
    lines, ts = wrap_banner(text, width - 20, ts, th, max_lines=3)
    lh = _text_box("Ag", ts, th)[1] + 4
    y = height // 2 - lh * len(lines) // 2
    for k, ln in enumerate(lines):
        tw = _text_box(ln, ts, th)[0]
        _text(img, ln, ((width - tw) // 2, y + lh * (k + 1)), (80, 80, 255), ts, th)
    return img


def frame_code_strip(index: int, bits: int = 20, cell: int = 16) -> np.ndarray:
    """A black/white strip (cell x bits*cell, BGR) encoding ``index`` in binary, most significant
    bit first, robust to JPEG compression. Used by the benchmark to read frame numbers back from
    the browser's screen; ``read_frame_code`` decodes it."""
    strip = np.zeros((cell, bits * cell, 3), np.uint8)
    for b in range(bits):
        if (int(index) >> (bits - 1 - b)) & 1:
            strip[:, b * cell:(b + 1) * cell] = 255
    return strip


def read_frame_code(strip_bgr_or_grey: np.ndarray, bits: int = 20, cell: int = 16) -> int:
    g = strip_bgr_or_grey if strip_bgr_or_grey.ndim == 2 else strip_bgr_or_grey.mean(axis=2)
    v = 0
    for b in range(bits):
        v = (v << 1) | int(g[cell // 4: 3 * cell // 4, b * cell + cell // 4: b * cell + 3 * cell // 4].mean() > 127)
    return v
