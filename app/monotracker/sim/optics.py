"""Photo-like imaging for the simulated camera: what real optics and sensors do to a frame.

The simple render of :class:`~monotracker.sim.camera_sim.SimulatedCamera` (flat colours, Gaussian
noise added to the 8-bit image) is what our detectors were tuned on; real frames differ in ways
that bias a colour-weighted centroid. :class:`Optics` switches on, for one camera:

Scene appearance (used by the renderer in ``camera_sim``):

* **gloss**: Blinn-Phong specular highlights on the balls (``ball_specular``, ``ball_shininess``)
  and on the skin (``skin_specular``), on top of the Lambert shading;
* **drapes**: the background is made of surgical drape panels with folds, colours from
  :data:`DRAPE_BGR` (``drapes``: ``"blue"``, ``"teal"``, ``"green-blue"``, ``"mixed"``); blue and
  teal drapes have positive green chromaticity, teal sits next to the balls' hue;
* **hair**: thin dark strands over the skin (``hair_density``: strands per 10 000 px);
* **gloves and steel**: hand occluders take glove colours from :data:`GLOVE_BGR` (latex, blue
  nitrile, green, brown), instruments are steel with a bright specular streak along the shaft.

Imaging chain (:class:`OpticsChain`, applied to the rendered image: display-space BGR float
0-255, or linear radiance with ``linear=True``, as the renderer hands it over so that its edges
mix in linear light): display -> linear radiance (``gamma``), lens blur (a defocus disc PSF of radius
``defocus_px``; the motion blur of the renderer comes before it), vignetting, an RGGB Bayer
mosaic, sensor noise in raw electrons (shot noise with ``full_well_e`` electrons at white, read
noise ``read_noise_e``), quantisation to 12 bits, edge-aware demosaicing (OpenCV ``_EA``),
gamma encoding to 8 bits, then JPEG at ``jpeg_quality`` (0 = none). Saturation clips at the full
well, so an over-exposed highlight is flat white.

Everything is deterministic: the noise of a frame is drawn from a generator seeded with the
camera's seed and the frame time. Cost at 1280x720: ~25-45 ms per frame on one core (JPEG and
the noise draw dominate), so the realistic render is opt-in for the live app.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: surgical drape colours (BGR, display space, nominal light)
DRAPE_BGR = {
    "blue": (150.0, 105.0, 45.0),         # classic blue drape: G > R, positive green chromaticity
    "teal": (120.0, 125.0, 30.0),         # teal / ceil blue: hue ~92 on OpenCV's 0-180 scale
    "green-blue": (110.0, 120.0, 45.0),   # green-blue (hue ~87): inside the default green band
    "light-blue": (175.0, 145.0, 100.0),
}
DRAPE_SETS = {"blue": ("blue",), "teal": ("teal",), "green-blue": ("green-blue",),
              "mixed": ("blue", "teal", "light-blue", "green-blue")}
#: glove colours (BGR): latex, blue nitrile, green surgical glove, brown latex
GLOVE_BGR = ((175.0, 195.0, 215.0), (185.0, 120.0, 60.0), (120.0, 160.0, 110.0), (95.0, 130.0, 170.0))
STEEL_BGR = (125.0, 122.0, 118.0)
HAIR_BGR = (30.0, 38.0, 50.0)


@dataclass(frozen=True)
class Optics:
    """Settings of the photo-like render (see the module docstring). Units: px, electrons."""

    # scene appearance
    drapes: str = "mixed"
    ball_specular: float = 0.9          # peak highlight, fraction of white
    ball_shininess: float = 60.0
    skin_specular: float = 0.15
    hair_density: float = 6.0           # strands per 10 000 px of image
    # imaging chain
    defocus_px: float = 1.5             # radius of the defocus disc PSF (0 = in focus)
    gamma: float = 2.2
    vignetting: float = 0.25            # relative fall-off at the image corners
    bayer: bool = True
    full_well_e: float = 4000.0         # electrons at white (shot noise sqrt(e))
    read_noise_e: float = 6.0
    jpeg_quality: int = 85              # 0 = no JPEG

    def __post_init__(self):
        if self.drapes not in DRAPE_SETS:
            raise ValueError(f"drapes must be one of {sorted(DRAPE_SETS)}, got {self.drapes!r}")
        if self.defocus_px < 0 or self.full_well_e <= 0 or not (0 <= self.jpeg_quality <= 100):
            raise ValueError("defocus_px >= 0, full_well_e > 0 and jpeg_quality in [0, 100] are required")


#: a few named presets for tests and benchmarks
PRESETS = {
    "photo": Optics(),
    "sharp": Optics(defocus_px=0.0, jpeg_quality=95),
    "degraded": Optics(defocus_px=2.5, full_well_e=1500.0, read_noise_e=10.0, jpeg_quality=70),
}


def disc_psf(radius_px: float, supersample: int = 8) -> np.ndarray:
    """Normalised defocus PSF: a uniform disc of ``radius_px`` (px), area-sampled on the pixel
    grid (float32, odd size). Radius < 0.3 px gives the identity kernel."""
    if radius_px < 0.3:
        return np.ones((1, 1), np.float32)
    n = int(np.ceil(radius_px + 0.5))
    size = 2 * n + 1
    s = supersample
    g = (np.arange(size * s) + 0.5) / s - 0.5 - n
    xx, yy = np.meshgrid(g, g)
    inside = (xx**2 + yy**2 <= radius_px**2).astype(np.float32)
    k = inside.reshape(size, s, size, s).mean(axis=(1, 3))
    return (k / k.sum()).astype(np.float32)


class OpticsChain:
    """The imaging chain of one camera (image size fixed at construction): :meth:`apply`."""

    def __init__(self, optics: Optics, image_size: tuple[int, int], seed: int = 0):
        self.optics = optics
        w, h = image_size
        self.size = (w, h)
        self.seed = int(seed)
        self.psf = disc_psf(optics.defocus_px)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
        vig = (1.0 - optics.vignetting * r2).astype(np.float32)
        self.vignette = cv2.merge([vig, vig, vig])
        self._enc = (np.linspace(0, 1, 4096) ** (1.0 / optics.gamma) * 255.0 + 0.5).astype(np.uint8)

    def to_linear(self, img: np.ndarray) -> np.ndarray:
        """Display-space BGR (0-255, float32) -> linear radiance (1.0 = white; highlights may
        exceed it)."""
        return cv2.pow(cv2.max(np.asarray(img, np.float32), 0.0) * np.float32(1.0 / 255.0), self.optics.gamma)

    def linear_colour(self, bgr) -> tuple:
        """One display-space BGR colour (0-255) -> linear radiance (tuple of 3 floats)."""
        return tuple(float(v) for v in (np.maximum(np.asarray(bgr, float), 0.0) / 255.0) ** self.optics.gamma)

    def apply(self, img: np.ndarray, key: float = 0.0, linear: bool = False) -> np.ndarray:
        """BGR float32 image -> the camera's 8-bit BGR output. ``img`` is display-space (0-255,
        may exceed 255 in highlights), or with ``linear`` already linear radiance (1.0 = white:
        the scene as the lens sees it, anti-aliased edges mixed in linear light as a pixel
        integrates photons). ``key`` (e.g. the frame time) seeds the noise of this frame."""
        o = self.optics
        lin = np.asarray(img, np.float32) if linear else self.to_linear(img)
        if self.psf.size > 1:
            lin = cv2.filter2D(lin, -1, self.psf, borderType=cv2.BORDER_REPLICATE)
        if o.vignetting:
            lin = cv2.multiply(lin, self.vignette)
        rng = np.random.default_rng([self.seed, int(round(abs(key) * 1e6)) % (2**62)])
        if o.bayer:
            h, w = lin.shape[:2]
            raw = np.empty((h, w), np.float32)
            raw[0::2, 0::2] = lin[0::2, 0::2, 2]      # RGGB
            raw[0::2, 1::2] = lin[0::2, 1::2, 1]
            raw[1::2, 0::2] = lin[1::2, 0::2, 1]
            raw[1::2, 1::2] = lin[1::2, 1::2, 0]
        else:
            raw = lin
        e = np.minimum(raw, np.float32(1.0)) * np.float32(o.full_well_e)
        sigma = cv2.sqrt(e + np.float32(o.read_noise_e**2))
        e += sigma * rng.standard_normal(e.shape, dtype=np.float32)
        code = np.clip(e * np.float32(4095.0 / o.full_well_e) + 0.5, 0, 4095).astype(np.uint16)
        if o.bayer:
            code = cv2.cvtColor(code, cv2.COLOR_BayerBG2BGR_EA)   # OpenCV's "BG" code reads RGGB
        out = np.take(self._enc, code, mode="clip")
        if o.jpeg_quality:
            ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(o.jpeg_quality)])
            out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        return out


# ---------------------------------------------------------------------- scene textures
def drape_background(optics: Optics, shape_hw: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """Low-resolution drape background (BGR float32): panels of the chosen drape colours split
    by a few slanted seams, with folds (sinusoidal shading) and weave noise."""
    h, w = shape_hw
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    colours = [np.array(DRAPE_BGR[c], np.float32) for c in DRAPE_SETS[optics.drapes]]
    out = np.empty((h, w, 3), np.float32)
    out[:] = colours[0]
    if len(colours) > 1:
        # seams: lines through random points; each side takes the next colour
        for _k, col in enumerate(colours[1:]):
            ang = rng.uniform(0, np.pi)
            p = rng.uniform([0.15 * w, 0.15 * h], [0.85 * w, 0.85 * h])
            side = (xx - p[0]) * np.sin(ang) - (yy - p[1]) * np.cos(ang) > 0
            out[side] = col
    shade = 0.8 + 0.2 * (xx / w) * (1 - 0.4 * yy / h)
    folds = 1 + 0.08 * np.sin(xx / rng.uniform(6, 12) + 0.9 * np.sin(yy / rng.uniform(9, 16)))
    tex = cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 1.5) * 0.04
    return out * (shade * folds + tex)[..., None]


def hair_layer(optics: Optics, image_size: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """Full-resolution hair coverage (float32 (h, w) in [0, 1]): thin curved dark strands, each
    8-40 px long, 1 px wide, anti-aliased; later multiplied by the skin coverage."""
    w, h = image_size
    layer = np.zeros((h, w), np.float32)
    n = int(optics.hair_density * w * h / 10000)
    for _ in range(n):
        p = rng.uniform([0, 0], [w, h])
        ang = rng.uniform(0, np.pi)
        length = rng.uniform(8, 40)
        bend = rng.uniform(-0.08, 0.08)
        pts = [p]
        for _ in range(int(length // 4)):
            ang += bend
            p = p + 4 * np.array([np.cos(ang), np.sin(ang)])
            pts.append(p)
        cv2.polylines(layer, [np.round(np.array(pts) * 16).astype(np.int32)], False, float(rng.uniform(0.4, 0.9)),
                      1, cv2.LINE_AA, shift=4)
    return np.clip(layer, 0.0, 1.0)


def specular(normals: np.ndarray, rays: np.ndarray, light: np.ndarray, shininess: float) -> np.ndarray:
    """Blinn-Phong specular term max(0, n . h)^shininess; ``normals`` and ``rays`` (..., 3) unit
    vectors in the camera frame (rays from the camera), ``light`` (3,) towards the light."""
    view = -rays
    half = light[None, :] + view.reshape(-1, 3)
    half /= np.linalg.norm(half, axis=1, keepdims=True) + 1e-12
    nh = np.clip(np.einsum("ij,ij->i", normals.reshape(-1, 3), half), 0.0, 1.0)
    return (nh**shininess).reshape(normals.shape[:-1])
