"""A dark band of skin beside a ball's unlit limb: contact-shadow evidence a small ball's edge rays miss (issue 28).

What it answers: the shading check (:mod:`.shading_check`) applies only to frames whose balls show
contact shadows, and it counted them only from the edge fit's left-out rays (a ray whose edge lies
off the outline with darker skin just beyond it). A ball imaged at ~8 px radius (a short lens near
the head: docs/vision.md "Other lenses") has one ray per ~1.6 px of outline, and the narrow band of
shadow that hugs its unlit limb is blurred into the limb's own darkening: its rays' edges move out
together, the fit follows them, and no single ray is left out. Its centre is then pushed
0.4-0.75 px towards the unlit side while the check does not look (the wide-lens trusted poses 1-2
mm off, docs/vision.md "A push not seen").

The reading: along :data:`RAYS` rays within +-:data:`HALF_ANGLE_DEG` of the ball's unlit direction
(away from its lit side: the shading shift, which points to the lit side), the skin's linear luma
near the ball (its colour blob's mean semi-axis + the frame's edge blur + :data:`NEAR_PX`) over the
skin further out (+ :data:`FAR_PX` instead), each offset's median over the rays; the same on the lit
side; the ball's **band ratio** is the unlit side's over the lit side's. Skin with no shadow beside
the ball reads ~1 on both sides whatever the lamp's gradient across the head; a band of shadow on
the unlit side reads below.

Where "near" lies matters, and it is not beyond the blur: the colour blob's outline lies inside the
edge fit's 50 % outline, so the near samples start about at the fitted edge (the wide-lens
renders: blob semi-axis + blur - fitted semi-axis ~0 px; our simulator's balls +0.32 to +0.43 px)
and read the blurred skirt of the unlit limb together with the band. Measured (``/work/scratch/s39``,
2026-12-03) against the alternatives: from the fitted outline + blur the reading never fires on the
wide-lens tuning frames (their trusted poses 1-2 mm off stay trusted); from the fitted outline + 0
it fires there but also on our simulator's dim, blurred ``degraded`` frames (no contact shadow;
right poses 94.4 -> 87.8 %, 3 seeds x 90 frames); from the blob's outline (this) it fires on the
former and not the latter (94.4 -> 94.4 %). The separation thus rests on a few tenths of a pixel:
docs/vision.md "A band of shadow beside the limb" gives every figure and what is not known.

The reading is evidence for the shading check (:func:`.shading_check.shadowed_share` takes the
larger of the rays' and the bands' shares), never a correction of a centre: a reading that fires
where there is no shadow costs reach (the check then asks the second readings' pose to agree), not
safety.
"""

from __future__ import annotations

import numpy as np

from .edge_fit import COLOUR_WEIGHTS, LINEAR_LUT

#: where the near skin is read, px beyond the ball's colour-blob radius plus the frame's edge blur
NEAR_PX = (0.0, 0.5, 1.0, 1.5)
#: where the skin further out is read, px beyond the colour-blob radius plus the edge blur
FAR_PX = 4.5
#: rays per side, spread over +- this many degrees about the unlit (and the lit) direction
RAYS = 7
HALF_ANGLE_DEG = 35.0
#: a ball whose band ratio is under this shows a band of shadow beside its unlit limb (0 = the
#: reading is not made: ``BlobRules.skin_band_ratio``, the detector before 2026-12-03)
BAND_RATIO = 0.85


def band_ratios(image_bgr: np.ndarray, centres_px, radii_px, lit_dirs, blur_px: float) -> np.ndarray:
    """The band ratios (see the module docstring) of ``n`` balls, (n,): ``centres_px`` (n, 2) their
    fitted centres (px, the image's own, distorted, coordinates), ``radii_px`` (n,) their colour
    blobs' mean semi-axes (px; ``ImageFiducial.axes_px``, not the edge fit's outline), ``lit_dirs``
    (n, 2) vectors towards their lit sides (their shading shifts, px; any length), ``blur_px`` the
    frame's edge blur (px). NaN for a ball where it cannot be read: no lit side (a zero shift),
    samples beyond the image, or skin that reads black. The samples are bilinear in linear
    radiance (the 8-bit values linearised at the four neighbouring pixels, then weighted), all
    balls at once."""
    c = np.asarray(centres_px, float).reshape(-1, 2)
    lit = np.asarray(lit_dirs, float).reshape(-1, 2)
    rad = np.asarray(radii_px, float).reshape(-1)
    n = len(c)
    out = np.full(n, np.nan)
    if not n or not np.isfinite(blur_px):
        return out
    base = np.arctan2(lit[:, 1], lit[:, 0])
    ang = np.deg2rad(np.linspace(-HALF_ANGLE_DEG, HALF_ANGLE_DEG, RAYS))
    # per ball: rows the unlit side's rays then the lit side's; columns the near offsets then the far one
    phi = np.concatenate([base[:, None] + np.pi + ang[None, :], base[:, None] + ang[None, :]], axis=1)
    s = rad[:, None] + max(float(blur_px), 0.0) + np.array([*NEAR_PX, FAR_PX])[None, :]
    px = c[:, 0, None, None] + np.cos(phi)[:, :, None] * s[:, None, :]          # (n, 2 RAYS, offsets)
    py = c[:, 1, None, None] + np.sin(phi)[:, :, None] * s[:, None, :]
    h, w = image_bgr.shape[:2]
    x0, y0 = np.floor(px).astype(int), np.floor(py).astype(int)
    inside = (x0 >= 0).all(axis=(1, 2)) & (y0 >= 0).all(axis=(1, 2)) & \
        (x0 + 1 < w).all(axis=(1, 2)) & (y0 + 1 < h).all(axis=(1, 2))
    inside &= (np.hypot(lit[:, 0], lit[:, 1]) > 0) & (rad > 0)
    if not inside.any():
        return out
    x0, y0, fx, fy = x0[inside], y0[inside], px[inside] - x0[inside], py[inside] - y0[inside]

    def luma(yy, xx):
        return LINEAR_LUT[image_bgr[yy, xx]] @ COLOUR_WEIGHTS[0]

    v = ((1 - fy) * ((1 - fx) * luma(y0, x0) + fx * luma(y0, x0 + 1))
         + fy * ((1 - fx) * luma(y0 + 1, x0) + fx * luma(y0 + 1, x0 + 1)))
    # each side's profile: the median over its rays at each offset (a hair or a drape's edge across
    # one or two rays does not move it), then the near offsets' mean over the far one
    un_p, lit_p = np.median(v[:, :RAYS], axis=1), np.median(v[:, RAYS:], axis=1)
    k = len(NEAR_PX)
    un, uf, ln, lf = un_p[:, :k].mean(1), un_p[:, k], lit_p[:, :k].mean(1), lit_p[:, k]
    ok = (uf > 1e-6) & (ln > 1e-6) & (lf > 1e-6)
    got = np.full(len(un), np.nan)
    got[ok] = (un[ok] / uf[ok]) / (ln[ok] / lf[ok])
    out[inside] = got
    return out
