"""A shaded ball's edge-fitted centre moved back towards the sphere's (issue 28).

Lit from one side, a ball's unlit limb is as dark as the contact shadow beside it, and the edge
fit reads part of that shadow as ball: its centre is pushed towards the unlit side. The colour
blob's contour (the ball's hue, blind to brightness) is pushed the other way. Measured on the
physically rendered tuning sets (Mitsuba 3 and Blender Cycles, every accepted whole ball of 3
frames per scene, 1602 balls), per ball:

* the error of the edge centre points away from the ball's lit side: its cosine with the
  direction ``u`` from the fitted centre to the brightness centroid inside 0.8 x the outline
  (the lit side) has median -0.82 (Blender) / -0.91 (Mitsuba);
* a linear model of the error on ``u``'s frame, fitted on each renderer's balls separately,
  gives the same answer on both (Mitsuba / Blender): along ``u`` 0.131 / 0.133 px plus
  0.45 / 0.48 x the blob contour's offset from the edge centre, across ``u`` 0.47 / 0.43 x that
  offset.

So the centre is moved by ``BLOB_WEIGHT`` x (blob centre - edge centre) + ``LIT_SHIFT_PX``
along ``u``. Fitted on Mitsuba, scored on Blender's balls: per-ball error 0.304 -> 0.228 px
(RMS per coordinate), the part common to a frame's balls (what no residual shows, and what moves
the pose) 0.271 -> 0.163 px; Mitsuba 0.307 -> 0.205, common 0.266 -> 0.153.

OPT-IN (``BlobRules.shading_shift``), not the default: it moves right centres elsewhere. On our
simulator (``benchmarks/camera_pipeline.py --quick``, row ``edge+shade``) the mean centre error
went from 0.022 to 0.209 px (clean) and 0.076 to 0.402 px (OR); on the independent single-ball
renders (``benchmarks/independent_optics.py --quick``, Lambert + Phong balls without a contact
shadow) from 0.060 to 0.341 px (sharp, whole balls). The push it undoes is the unlit limb merged
with a contact shadow, not shading as such, and nothing here tells the two apart. On the rendered
tuning sets themselves it lowered the mean centre error on 18 of 20 set x condition rows but not
the pose's trust: trusted frames 1-2 mm off went from 3 to 7 of 142-153 (a smaller per-ball
scatter with the common shift left). See docs/vision.md.

A ball with no visible shading (``|u|`` under ``MIN_LIT``, brightness centroid within 5 % of
the radius of the centre: a ball of flat colour or lit head-on) keeps its edge centre; the shift
is never more than ``MAX_SHIFT`` x the ball's radius (a blob cut by a finger or an instrument,
whose contour is not the ball's, moves nothing beyond that).
"""

from __future__ import annotations

import numpy as np

#: weight of the blob contour's centre (the colour mask's ellipse) against the edge fit's
BLOB_WEIGHT = 0.46
#: shift towards the lit side (px)
LIT_SHIFT_PX = 0.13
#: smallest lit-side offset (brightness centroid from the centre, x the radius) that counts as
#: a shaded ball
MIN_LIT = 0.05
#: no shift beyond this share of the ball's radius (px / px)
MAX_SHIFT = 0.15


def lit_side(grey: np.ndarray, centre_px, radius_px: float) -> np.ndarray:
    """The brightness centroid inside 0.8 x ``radius_px`` of ``centre_px`` (image px, OpenCV
    pixel centres), relative to it and over the radius: (2,) (0 where the crop leaves the image
    or is flat). ``grey``: one channel, or BGR (its channels' mean is the brightness)."""
    cx, cy = float(centre_px[0]), float(centre_px[1])
    r = 0.8 * float(radius_px)
    x0, y0 = int(np.floor(cx - r)), int(np.floor(cy - r))
    x1, y1 = int(np.ceil(cx + r)) + 1, int(np.ceil(cy + r)) + 1
    h, w = grey.shape[:2]
    if r <= 1.0 or x0 < 0 or y0 < 0 or x1 > w or y1 > h:
        return np.zeros(2)
    crop = grey[y0:y1, x0:x1].astype(np.float64)
    if crop.ndim == 3:
        crop = crop.mean(axis=2)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    dx, dy = xx - cx, yy - cy
    inside = dx * dx + dy * dy <= r * r
    v = crop[inside]
    wgt = v - v.min()
    total = float(wgt.sum())
    if not total > 0:
        return np.zeros(2)
    return np.array([np.sum(wgt * dx[inside]), np.sum(wgt * dy[inside])]) / total / float(radius_px)


def shaded_centre(grey: np.ndarray, edge_centre_px, blob_centre_px, radius_px: float) -> tuple[np.ndarray, float]:
    """The centre of a ball whose edge fit gave ``edge_centre_px`` and whose colour blob's
    contour ellipse is centred at ``blob_centre_px`` (px), its image radius ``radius_px``:
    (centre (2,), the shift applied px). Unchanged for a ball without visible shading."""
    edge = np.asarray(edge_centre_px, float)
    u = lit_side(grey, edge, radius_px)
    lit = float(np.hypot(*u))
    if lit < MIN_LIT:
        return edge, 0.0
    shift = BLOB_WEIGHT * (np.asarray(blob_centre_px, float) - edge) + LIT_SHIFT_PX * u / lit
    size = float(np.hypot(*shift))
    cap = MAX_SHIFT * float(radius_px)
    if size > cap:
        shift *= cap / size
        size = cap
    return edge + shift, size
