"""Ball images rendered independently of ``monotracker.sim``: a second judge for edge-fit centres.

Our simulator and our detector were written by the same hands, so an error both make (a wrong
idea of how blur, demosaicing or JPEG act on an edge) cancels. This renderer shares no code and
few choices with ``monotracker.sim``:

* **scene**, supersampled 8 x 8 per pixel: a ball imaged as an ellipse (axis ratio 0.88-1, any
  angle) of known centre, Lambert shading with a random light direction plus ambient, a Phong
  highlight that may clip; behind it two background colours (skin tones, drapes, gauze, glove
  colours of our own choosing) split by a straight boundary that passes through the ball or just
  outside its edge (a ball on, or next to, the head's outline), each with its own brightness
  gradient and a faint smooth texture; the ball anywhere within 8 px of the image's middle (every
  phase of JPEG's 8 / 16 px block grid);
* **optics** in linear light on the supersampled grid: a defocus PSF (uniform disc) followed by
  a Gaussian (aberrations, sensor crosstalk), then integration over each pixel's area;
* **sensor**: RGGB Bayer mosaic, shot noise (full well in electrons) and read noise, 12-bit
  quantisation, OpenCV's bilinear demosaicing (the simulator uses the edge-aware one), the sRGB
  transfer curve (piecewise; the simulator and the edge fit use a pure 2.2 power law);
* **JPEG** through ``cv2.imencode`` (4:2:0 chroma) at a given quality;
* optionally a straight-edged **occluder** in front of the ball (:class:`Occluder`), the
  ellipse's shape given (a sphere's at its place, :func:`sphere_shape`), and whole frames:
  :func:`render_in_frame` (one ball somewhere in a 1280 x 720 frame) and :func:`render_scene`
  (spheres at their exact image ellipses, :func:`sphere_image_ellipse`, for the pose pipeline).

The truth is the ellipse's centre (px, OpenCV convention: pixel centres at integers; a sample
of the supersampled grid at (i + 0.5) / 8 - 0.5), which is what a detector must report: the
registration corrects a sphere's image-ellipse centre to the projected sphere centre. The
shading takes the surface normal from the ellipse's normalised coordinates (a sphere's, squeezed
with the ellipse): shading only scales the ball's colour, it does not move the silhouette.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: linear-light BGR albedos (0-1) of our own choosing, none copied from monotracker.sim (a green
#: drape is left out: in the balls' own colour band it merges with them, which is the ball
#: colour's problem, not the centre's)
BACKGROUNDS = {
    "fair skin": (0.38, 0.47, 0.66),
    "dark skin": (0.07, 0.10, 0.17),
    "blue drape": (0.42, 0.16, 0.05),
    "teal drape": (0.30, 0.28, 0.04),
    "white gauze": (0.70, 0.72, 0.70),
    "blue glove": (0.55, 0.25, 0.10),
    "steel": (0.20, 0.20, 0.19),
}
BALL_ALBEDO = (0.04, 0.42, 0.07)   # a saturated green dye, linear BGR
SS = 8                             # supersampling per pixel and axis
#: the two-colour boundary passes through the ball or at most this far (px) outside its edge:
#: a ball glued to the skin next to the head's outline sees the drape just beyond its edge
OUTLINE_BEYOND_PX = 5.0


@dataclass(frozen=True)
class Imaging:
    """Optics and sensor of one render. Units: px (image pixels), electrons."""

    defocus_px: float = 1.5        # radius of the defocus disc
    gauss_px: float = 0.5          # sigma of the Gaussian after it
    full_well_e: float = 6000.0
    read_noise_e: float = 4.0
    bayer: bool = True
    jpeg_quality: int = 85         # 0 = no JPEG
    exposure: float = 0.8          # scene radiance 1.0 -> this share of full scale


def _disc_kernel(radius: float) -> np.ndarray:
    n = int(np.ceil(radius)) + 1
    g = np.arange(-n, n + 1, dtype=np.float64)
    xx, yy = np.meshgrid(g, g)
    # area-weighted disc: a 4 x 4 sub-sample of each kernel cell
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    k = np.zeros_like(xx)
    for dx in sub:
        for dy in sub:
            k += (xx + dx) ** 2 + (yy + dy) ** 2 <= radius**2
    return (k / k.sum()).astype(np.float32)


def _srgb_encode(lin: np.ndarray) -> np.ndarray:
    lin = np.clip(lin, 0.0, 1.0)
    return np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)


@dataclass(frozen=True)
class Occluder:
    """A straight-edged object in front of the ball (a glove's finger, an instrument, a drape's
    fold): it hides the cap of the ball beyond a chord ``depth`` (share of the ball's radius
    along the chord's normal, 0-1) from the edge, at an angle drawn at random, and everything
    behind it beyond that line. ``colour``: a name from :data:`BACKGROUNDS`."""

    depth: float = 0.25
    colour: str = "blue glove"


def render_ball(rng: np.random.Generator, radius_px: float, imaging: Imaging = Imaging(),
                split: bool = True, size: int = 96, backgrounds: tuple | None = None,
                gradient_per_px: float = 0.004, occluder: Occluder | None = None,
                truth: dict | None = None, shape: tuple | None = None,
                centre_px: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One uint8 BGR image (size x size) with one ball of ``radius_px`` (semi-major axis, px)
    within 8 px of its middle (size >= 2 * radius + 40 leaves room for the edge fit's rays);
    returns (image, true ellipse centre (2,) px). ``split``: two background colours with their
    boundary through the ball or up to :data:`OUTLINE_BEYOND_PX` beyond its edge (else one
    colour); ``backgrounds``: the two names from :data:`BACKGROUNDS` (default: drawn at
    random); ``gradient_per_px``: the largest brightness gradient of each background along x
    and y (relative change per px; each drawn uniformly within +-this); ``occluder``: an
    :class:`Occluder` in front of the ball (None: none); ``truth``: a dict that receives the true
    ellipse ``axes`` (semi-major, semi-minor px), ``angle_rad`` (of the major axis, from +x
    towards +y) and, with an occluder, ``cut_normal`` (unit 2-vector from the centre towards the
    hidden cap); ``shape``: (minor / major, major axis angle rad from +x towards +y) of the
    ball's ellipse (e.g. a sphere's at some place in a camera's image; None: drawn at random);
    ``centre_px``: the ellipse's centre in the image (px; None: drawn within 8 px of the middle)."""
    names = list(BACKGROUNDS)
    if backgrounds is None:
        i, j = rng.choice(len(names), 2, replace=False)
        backgrounds = (names[i], names[j])
    # anywhere within one JPEG MCU (16 px) and Bayer period of the middle: the ball must not sit
    # at the same place on the 8 x 8 / 16 x 16 block grid in every render
    c = size / 2 + rng.uniform(-8.0, 8.0, 2)
    if centre_px is not None:
        c = np.asarray(centre_px, float)
    a = radius_px
    b = a * rng.uniform(0.88, 1.0)
    th = rng.uniform(0, np.pi)
    if shape is not None:
        b, th = a * float(shape[0]), float(shape[1])
    n = size * SS
    g = (np.arange(n) + 0.5) / SS - 0.5                     # hi-res sample -> image px
    xx, yy = np.meshgrid(g, g)
    dx, dy = xx - c[0], yy - c[1]
    u = dx * np.cos(th) + dy * np.sin(th)
    v = -dx * np.sin(th) + dy * np.cos(th)
    rho2 = (u / a) ** 2 + (v / b) ** 2
    inside = rho2 <= 1.0
    # sphere-like shading on the ellipse: normal from the normalised coordinates
    nz = np.sqrt(np.clip(1.0 - rho2, 0.0, 1.0))
    nx, ny = u / a, v / b
    tilt, az = rng.uniform(0.3, 0.9), rng.uniform(0, 2 * np.pi)
    L = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    lam = np.clip(nx * L[0] + ny * L[1] + nz * L[2], 0.0, None)
    hv = L + np.array([0.0, 0.0, 1.0])
    hv /= np.linalg.norm(hv)
    spec = np.clip(nx * hv[0] + ny * hv[1] + nz * hv[2], 0.0, None) ** 40 * rng.uniform(0.3, 1.2)
    ball = (0.15 + 0.85 * lam)[..., None] * np.array(BALL_ALBEDO) + spec[..., None]
    # background: one or two colours, each with its own gradient and a faint smooth texture
    col1, col2 = np.array(BACKGROUNDS[backgrounds[0]]), np.array(BACKGROUNDS[backgrounds[1]])
    gm = gradient_per_px
    grad = 1.0 + rng.uniform(-gm, gm) * (xx - c[0]) + rng.uniform(-gm, gm) * (yy - c[1])
    tex = cv2.GaussianBlur(rng.normal(0, 1, (size, size)).astype(np.float32), (0, 0), 2.0)
    tex = cv2.resize(tex / (tex.std() + 1e-9), (n, n), interpolation=cv2.INTER_LINEAR)
    bg = (grad * (1.0 + 0.03 * tex))[..., None] * col1
    if split:
        phi = rng.uniform(0, 2 * np.pi)
        d = rng.uniform(-1.0, 1.0) * (a + OUTLINE_BEYOND_PX)
        side = (dx * np.cos(phi) + dy * np.sin(phi)) > d
        grad2 = 1.0 + rng.uniform(-gm, gm) * (xx - c[0]) + rng.uniform(-gm, gm) * (yy - c[1])
        bg = np.where(side[..., None], (grad2 * (1.0 + 0.03 * tex))[..., None] * col2, bg)
    scene = np.where(inside[..., None], ball, bg).astype(np.float32)
    if truth is not None:
        truth.update(axes=(a, b), angle_rad=th)
    if occluder is not None:
        # the chord lies ``depth`` of the radius (along its normal) inside the ball's edge: the
        # ellipse's extent along the normal n is sqrt((a n_u)^2 + (b n_v)^2)
        psi = rng.uniform(0, 2 * np.pi)
        nrm = np.array([np.cos(psi), np.sin(psi)])
        nu, nv = nrm[0] * np.cos(th) + nrm[1] * np.sin(th), -nrm[0] * np.sin(th) + nrm[1] * np.cos(th)
        extent = np.hypot(a * nu, b * nv)
        hidden = (dx * nrm[0] + dy * nrm[1]) > (1.0 - occluder.depth) * extent
        col = np.array(BACKGROUNDS[occluder.colour])
        grad3 = 1.0 + rng.uniform(-gm, gm) * (xx - c[0]) + rng.uniform(-gm, gm) * (yy - c[1])
        scene = np.where(hidden[..., None], ((grad3 * (1.0 + 0.03 * tex))[..., None] * col).astype(np.float32),
                         scene)
        if truth is not None:
            truth.update(cut_normal=nrm)
    # optics on the supersampled grid (linear light), then pixel integration
    if imaging.defocus_px > 0:
        scene = cv2.filter2D(scene, -1, _disc_kernel(imaging.defocus_px * SS), borderType=cv2.BORDER_REFLECT)
    if imaging.gauss_px > 0:
        scene = cv2.GaussianBlur(scene, (0, 0), imaging.gauss_px * SS, borderType=cv2.BORDER_REFLECT)
    lin = scene.reshape(size, SS, size, SS, 3).mean(axis=(1, 3)) * imaging.exposure
    # sensor: Bayer RGGB (BGR channel order: 0 = B, 1 = G, 2 = R), shot + read noise, 12 bits
    e = lin * imaging.full_well_e
    if imaging.bayer:
        raw = np.empty((size, size), np.float64)
        raw[0::2, 0::2] = e[0::2, 0::2, 2]      # R
        raw[0::2, 1::2] = e[0::2, 1::2, 1]      # G
        raw[1::2, 0::2] = e[1::2, 0::2, 1]      # G
        raw[1::2, 1::2] = e[1::2, 1::2, 0]      # B
        raw = rng.poisson(np.clip(raw, 0, None)) + rng.normal(0, imaging.read_noise_e, raw.shape)
        dn = np.clip(np.round(raw / imaging.full_well_e * 4095), 0, 4095).astype(np.uint16)
        # OpenCV names Bayer patterns from the second row's second and third pixels: RGGB is "BG"
        rgb = cv2.cvtColor(dn, cv2.COLOR_BayerBG2BGR).astype(np.float64) / 4095
    else:
        e = rng.poisson(np.clip(e, 0, None)) + rng.normal(0, imaging.read_noise_e, e.shape)
        rgb = np.clip(np.round(e / imaging.full_well_e * 4095), 0, 4095) / 4095
    img = np.clip(np.round(_srgb_encode(rgb) * 255), 0, 255).astype(np.uint8)
    if imaging.jpeg_quality > 0:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(imaging.jpeg_quality)])
        img = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return img, c


#: the pinhole camera of :func:`render_in_frame` (no distortion): focal length (px), principal
#: point (px), image size (w, h px)
FRAME_F_PX = 1100.0
FRAME_PRINCIPAL_PX = (640.0, 360.0)
FRAME_SIZE = (1280, 720)
#: its intrinsic matrix (px; no distortion): ``CameraModel(FRAME_K, np.zeros(5), FRAME_SIZE)``
FRAME_K = np.array([[FRAME_F_PX, 0.0, FRAME_PRINCIPAL_PX[0]], [0.0, FRAME_F_PX, FRAME_PRINCIPAL_PX[1]],
                    [0.0, 0.0, 1.0]])


def sphere_shape(xy_px, minor_px: float) -> tuple[float, float]:
    """(minor / major, major axis angle rad from +x towards +y) of a sphere's image ellipse at
    ``xy_px`` with minor semi-axis ``minor_px`` under the camera of :func:`render_in_frame`:
    the cone-plane formula, minor / major = sqrt(cos^2 theta - sin^2 alpha) / cos alpha with
    theta the angle of the ball's ray from the optical axis and alpha its angular radius (from
    b = f sin(alpha) / sqrt(cos^2 theta - sin^2 alpha)); the major axis is radial."""
    dx, dy = xy_px[0] - FRAME_PRINCIPAL_PX[0], xy_px[1] - FRAME_PRINCIPAL_PX[1]
    theta = np.arctan(np.hypot(dx, dy) / FRAME_F_PX)
    q = (minor_px / FRAME_F_PX) ** 2
    s2 = q * np.cos(theta) ** 2 / (1 + q)                   # sin^2 alpha
    return float(np.sqrt(np.cos(theta) ** 2 - s2) / np.sqrt(1 - s2)), float(np.arctan2(dy, dx))


def render_in_frame(rng: np.random.Generator, imaging: Imaging = Imaging(), occluder: Occluder | None = None,
                    radius_px: tuple = (7.0, 13.0)) -> tuple[np.ndarray, np.ndarray]:
    """A FRAME_SIZE uint8 BGR frame, plain grey but for one :func:`render_ball` image (96 x 96,
    one background colour) pasted at a random place, its ball drawn with the outline a sphere
    has there (:func:`sphere_shape`), of semi-major axis uniform in ``radius_px``; returns
    (frame, true ellipse centre (2,) px)."""
    radius = float(rng.uniform(*radius_px))
    ox, oy = int(rng.integers(0, FRAME_SIZE[0] - 96)), int(rng.integers(0, FRAME_SIZE[1] - 96))
    shape = sphere_shape((ox + 48, oy + 48), radius * 0.95)
    patch, c = render_ball(rng, radius, imaging, split=False, occluder=occluder, shape=shape)
    frame = np.full((FRAME_SIZE[1], FRAME_SIZE[0], 3), 128, np.uint8)
    frame[oy:oy + 96, ox:ox + 96] = patch
    return frame, c + [ox, oy]


def sphere_image_ellipse(X_cam, radius_mm: float) -> tuple[np.ndarray, float, float, float]:
    """The exact image ellipse of a sphere (centre ``X_cam`` camera frame mm, z > 0, radius mm)
    under the camera of :func:`render_in_frame`: (centre (2,) px, semi-major px, semi-minor px,
    major axis angle rad). The rays p = (x, y, 1) tangent to the sphere satisfy
    (p . X)^2 = |p|^2 (|X|^2 - R^2): a conic in the normalised image plane; its centre and axes
    are mapped to pixels with the focal length and principal point."""
    X = np.asarray(X_cam, float)
    C = np.outer(X, X) - (X @ X - radius_mm**2) * np.eye(3)   # p^T C p = 0
    A2, b2, c0 = C[:2, :2], C[:2, 2], C[2, 2]
    centre = -np.linalg.solve(A2, b2)
    k = centre @ A2 @ centre + 2 * b2 @ centre + c0             # conic at its centre
    w, V = np.linalg.eigh(-A2 / k)                               # (q - c)^T (-A2 / k) (q - c) = 1
    axes = 1.0 / np.sqrt(w)                                      # w ascending: major first
    major = V[:, 0]
    f, (cx, cy) = FRAME_F_PX, FRAME_PRINCIPAL_PX
    return (np.array([cx, cy]) + f * centre, float(f * axes[0]), float(f * axes[1]),
            float(np.arctan2(major[1], major[0])))


def render_scene(rng: np.random.Generator, X_cam: np.ndarray, radius_mm: float, imaging: Imaging = Imaging(),
                 occluders: dict | None = None, background: str = "fair skin") -> tuple[np.ndarray, np.ndarray]:
    """A FRAME_SIZE uint8 BGR frame of spheres (centres ``X_cam`` (n, 3) camera frame mm, radius
    mm) seen by the camera of :func:`render_in_frame`, each rendered by :func:`render_ball` at its
    exact image ellipse (:func:`sphere_image_ellipse`) in a 96 x 96 patch of ``background``
    pasted into a plain frame; ``occluders``: {ball index: :class:`Occluder`}. Returns (frame,
    true ellipse centres (n, 2) px). Balls must be >= 48 px inside the frame and >= 96 px apart."""
    frame = np.full((FRAME_SIZE[1], FRAME_SIZE[0], 3), 128, np.uint8)
    centres = []
    for i, X in enumerate(np.asarray(X_cam, float)):
        c, a, b, th = sphere_image_ellipse(X, radius_mm)
        o = np.floor(c).astype(int) - 48
        patch, cc = render_ball(rng, a, imaging, split=False, backgrounds=(background, background),
                                occluder=(occluders or {}).get(i), shape=(b / a, th), centre_px=c - o)
        frame[o[1]:o[1] + 96, o[0]:o[0] + 96] = patch
        centres.append(cc + o)
    return frame, np.array(centres)
