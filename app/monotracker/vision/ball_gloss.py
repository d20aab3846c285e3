"""Whether a frame's balls are glossy: a lamp's mirror image (a specular highlight) in their cores.

What it answers (issue 28): on Blender Cycles' planner-placed tuning frames, the default trust
model trusted poses 1-1.75 mm off at an 80 mm-deep target in 36 of 274 trusted frames, 25 of them
in one scene of glossy balls (a smooth clear coat) beside contact shadows: the balls' edge centres
were pushed 0.3-0.8 px towards the shadows, and with 5-6 balls the pose absorbed the pattern. A
stronger cover for frames of few balls (``TrackerConfig.few_balls`` 6, ``few_balls_cover`` 2.0)
removes nearly all of them, but costs about 4 in 10 of the scenes trusted within 1 mm at frame 8
when applied to every frame; applied only to scenes of glossy balls (read from the scene's
specification, an oracle) it kept nearly all the reach. This module is the frame's own reading
of that finish.

The cue: a smooth coat mirrors the OR lamp as a small bright spot inside the ball's outline; a
rough (matte) coat spreads it into a soft gradient. Per ball, :func:`highlight_ratio` is the
brightest pixel's brightness (the BGR channels' mean) inside ``CORE`` x the ball's radius over the
median brightness there. Measured on the rendered TUNING sets (Mitsuba 3 and Blender Cycles, every
whole ball of frame 1, 1529 balls; a frame's value is its balls' median): Blender and Mitsuba's
planner-placed frames (balls of 9-15 px radius) glossy 1.77-3.48, matte 1.25-1.93 (one matte
clutter frame over 1.8 of 48); Mitsuba's far frames (balls of 5-9 px) overlap: glossy 1.20-2.91,
matte 1.21-1.84 (a highlight of one pixel blurred by defocus reads as matte). A frame read as
glossy gets the stronger cover; one read as matte keeps the default, so a misreading either way
costs no more than the default's behaviour or some reach (``TrackerConfig.glossy_highlight_ratio``).
"""

from __future__ import annotations

import numpy as np

from .shading_check import shadows_seen

#: what the operator may say of the kit's balls (``TrackerConfig.ball_finish``): ``read`` (the
#: default: each frame's highlight reading decides), ``matte`` (never the glossy frames' cover),
#: ``glossy`` (the glossy frames' cover wherever the balls show contact shadows, read or not:
#: for far cameras whose highlights are too small to read)
FINISHES = ("read", "matte", "glossy")

#: the core searched for the highlight, x the ball's image radius (the limb's own shading and
#: the edge's blur stay out)
CORE = 0.75


def highlight_ratio(image: np.ndarray, centre_px, radius_px: float) -> float:
    """The brightest pixel inside ``CORE`` x ``radius_px`` of ``centre_px`` (image px, OpenCV
    pixel centres) over the median there, brightness = the channels' mean (``image`` BGR or one
    channel); NaN where the core leaves the image, holds under 5 pixels, or is black."""
    cx, cy, r = float(centre_px[0]), float(centre_px[1]), CORE * float(radius_px)
    x0, y0 = int(np.floor(cx - r)), int(np.floor(cy - r))
    x1, y1 = int(np.ceil(cx + r)) + 1, int(np.ceil(cy + r)) + 1
    h, w = image.shape[:2]
    if not r > 0 or x0 < 0 or y0 < 0 or x1 > w or y1 > h:
        return float("nan")
    crop = image[y0:y1, x0:x1]
    crop = crop.mean(axis=2) if crop.ndim == 3 else crop.astype(np.float64)
    dx, dy = np.arange(x0, x1) - cx, np.arange(y0, y1) - cy
    core = crop[dy[:, None] ** 2 + dx[None, :] ** 2 <= r * r]
    if core.size < 5:
        return float("nan")
    med = float(np.median(core))
    return float(core.max()) / med if med > 0 else float("nan")


def frame_highlight(features: list) -> float:
    """A frame's highlight reading: the median of its matched balls' ``highlight_ratio``
    features (NaN where none has one)."""
    v = np.array([float(f.get("highlight_ratio", np.nan)) for f in features], float)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else float("nan")


def reads_glossy(features: list, threshold: float, still: tuple = ()) -> bool:
    """Whether a frame's balls read as glossy: the frame's :func:`frame_highlight` or one of
    the still head's last readings (``still``: their values; a still head keeps its balls and
    lamps) at least ``threshold``; never where ``threshold`` <= 0 (off)."""
    if not threshold > 0:
        return False
    readings = [frame_highlight(features), *still]
    return any(np.isfinite(v) and v >= threshold for v in readings)


def wider_cover(features: list, threshold: float, min_shadow_share: float | None,
                still_highlights: tuple = (), still_shadow_shares: tuple = (), finish: str = "read") -> bool:
    """The one verdict on a frame's few-ball cover: whether it takes the glossy frames' wider
    one (``TrackerConfig.glossy_few_balls``, ``glossy_few_balls_cover``). Its balls (their
    detection features) must read as glossy (:func:`reads_glossy`, with ``still_highlights``)
    and, unless ``min_shadow_share`` is None, show contact shadows as the shading check counts
    them: :func:`.shading_check.shadowed_share` at least ``min_shadow_share`` in this frame or in
    one of ``still_shadow_shares`` (a still head's last frames). The push the cover answers is a
    glossy limb beside a shadow; a glossy ball on its own (our simulator's specular balls) is
    read right. ``finish`` (:data:`FINISHES`): ``matte`` never, ``glossy`` without the reading
    (the shadow condition still applies), ``read`` as above; ``ValueError`` for another."""
    if finish not in FINISHES:
        raise ValueError(f"ball finish must be one of {', '.join(FINISHES)}, not {finish!r}")
    if finish == "matte":
        return False
    if finish == "read" and not reads_glossy(features, threshold, still_highlights):
        return False
    if min_shadow_share is None:
        return True
    return shadows_seen(features, still_shadow_shares, min_shadow_share)
