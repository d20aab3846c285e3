"""Scene specifications of the physically based frame sets: what is in each scene, from a seed.

A :class:`SceneSpec` says everything the renderer needs (no randomness after this point), as
plain JSON-ready values, so that a scene has a stable hash (:func:`scene_hash`) that names its
cached render. Frames: the CT's LPS millimetres are the world frame; ``T_cam_ct`` maps CT mm
into the OpenCV camera frame (x right, y down, z forward, mm); colours are *linear* RGB
reflectances or radiances (0-1), never display values.

Scene families (:func:`make_spec`; choices written down because the issue leaves them open):

* **head**: the sample phantom's skin ellipsoid (:class:`~monotracker.sim.phantom.HeadPhantom`,
  72 x 92 x 86 mm, neck cut) with a textured rough-dielectric skin; fiducials: the phantom's
  nine balls, or 7-9 balls at random places within 40 deg of the patch centre (head-like
  layouts), 8 mm balls (radius 4 mm) of the kit's green, one finish per scene: ``matte`` (a
  rough coat) or ``glossy`` (a smooth coat that mirrors the lamps);
* **camera**: the default camera's intrinsics and distortion (1280 x 720, f = 1100 px), 300-800
  mm from the fiducials' centroid, viewing direction up to 45 deg off the patch's normal, any
  roll, the centroid anywhere in the central half of the image;
* **light**: one or two large round OR lamps (area lights, radius 200-350 mm, 0.9-1.3 m away,
  10-45 deg off the patch normal and never on the camera's axis) and an ambient term;
* **drapes**: a folded sheet behind the head in two or three panels and a folded towel round the
  head below the fiducial patch, colours from :data:`DRAPE_RGB` (one, ``or-green``, close to the
  balls' hue);
* **kinds**: ``clean`` (head, balls, drapes, hair at the edge of the shaved patch), ``OR`` (+ one
  or two gloved fingers and a steel instrument over balls, more hair), ``clutter`` (OR + green
  strays: a flat round sticker, a marker cap, a bigger ball, an LED; dense hair, loose strands
  across the patch).

**Split** (issue 28): ``tuning`` scenes (seeds from 1000, lamps family A: one lamp, warm 4300 K;
skins A: light, freckled; hair dark brown) may be looked at and tuned on by anyone;
``held_out`` scenes (seeds from 900000, lamps family B: two lamps, 5000 K + 4000 K, more
ambient; skins B: olive-brown, mottled, shinier; hair black or blond) are only ever scored.
``train`` scenes (seeds from 500000, for learning; family T, chosen before any scoring): 1-3
lamps of 2700-6500 K with shares 0.3-1.0, ambient 0.01-0.2 tinted 2700-8000 K; skin sRGB
(235, 190, 160) x 0.35-1.05 with +-10 % per channel, roughness 0.2-0.75, specular 0.2-0.7; hair
any of the three colours.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from monotracker.geometry import invert_transform, look_at, rotation_about_axis
from monotracker.sim.phantom import HeadPhantom, default_phantom

#: bump when the renderer's output for the same spec changes (part of every scene's hash)
RENDERER_VERSION = "pbr-1"
SPLITS = ("tuning", "held_out", "train")
KINDS = ("clean", "OR", "clutter")
#: first seed of each split: disjoint ranges, so no held-out scene is ever a tuning scene
SPLIT_SEED0 = {"tuning": 1000, "held_out": 900000, "train": 500000}


def srgb_to_linear(rgb) -> list[float]:
    """Display sRGB (0-255) -> linear (0-1), the piecewise sRGB curve."""
    c = np.asarray(rgb, float) / 255.0
    return [float(v) for v in np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)]


#: the kit's green dye (display sRGB 45, 160, 40 as the simulator's), linear RGB
BALL_RGB = srgb_to_linear((40, 160, 45))
#: surgical drape colours, linear RGB ("or-green" sits next to the balls' hue)
DRAPE_RGB = {
    "blue": srgb_to_linear((45, 105, 150)),
    "light-blue": srgb_to_linear((100, 145, 175)),
    "teal": srgb_to_linear((30, 125, 120)),
    "or-green": srgb_to_linear((70, 125, 95)),
    "green-blue": srgb_to_linear((45, 120, 110)),
}
#: glove colours, linear RGB: latex, blue nitrile, brown latex, green (clutter only)
GLOVE_RGB = {"latex": srgb_to_linear((215, 195, 170)), "nitrile": srgb_to_linear((70, 120, 190)),
             "brown": srgb_to_linear((170, 125, 90)), "green": srgb_to_linear((110, 160, 120))}
#: per split: lamp family, skin family, hair colours
FAMILIES = {
    "tuning": {"lamps": "A", "skin": "A", "hair": ("dark-brown",)},
    "held_out": {"lamps": "B", "skin": "B", "hair": ("black", "blond")},
    "train": {"lamps": "T", "skin": "T", "hair": ("dark-brown", "black", "blond")},
}
HAIR_RGB = {"dark-brown": srgb_to_linear((60, 42, 30)), "black": srgb_to_linear((25, 22, 20)),
            "blond": srgb_to_linear((190, 160, 110))}


@dataclass(frozen=True)
class Lamp:
    """A round area light: centre (CT mm), unit normal pointing at the head, radius mm, linear
    RGB colour (luminance ~1) and ``irradiance`` it gives at the fiducials' centroid (relative)."""

    centre: tuple
    normal: tuple
    radius_mm: float
    rgb: tuple
    irradiance: float


@dataclass(frozen=True)
class Capsule:
    """A gloved finger: a cylinder of ``radius_mm`` from ``tip`` (the centre of its round end,
    CT mm) along ``direction`` (unit) for ``length_mm``, closed by a sphere at the tip."""

    tip: tuple
    direction: tuple
    radius_mm: float
    length_mm: float
    glove: str


@dataclass(frozen=True)
class Rod:
    """A steel instrument shaft: a cylinder from ``start`` to ``end`` (CT mm), ``radius_mm``,
    GGX roughness ``roughness``."""

    start: tuple
    end: tuple
    radius_mm: float
    roughness: float


@dataclass(frozen=True)
class Stray:
    """A green object that is not a fiducial: ``shape`` "sticker" (flat disc on the skin),
    "cap" (closed cylinder lying on the skin), "ball" (a sphere of another size) or "led" (a
    small emitting sphere); ``centre`` CT mm, ``axis`` unit (disc normal / cylinder axis),
    ``size_mm`` (radius), ``length_mm`` (cap only)."""

    shape: str
    centre: tuple
    axis: tuple
    size_mm: float
    length_mm: float = 0.0


@dataclass(frozen=True)
class Skin:
    """Skin appearance: ``family`` A or B, base linear RGB, GGX ``roughness``, ``specular``
    (principled BSDF), texture seed."""

    family: str
    base_rgb: tuple
    roughness: float
    specular: float
    texture_seed: int


@dataclass(frozen=True)
class SceneSpec:
    """Everything in one scene (see the module docstring). Units mm, colours linear RGB.

    ``T_cam_ct`` (4x4 nested tuples) CT LPS mm -> OpenCV camera mm; ``K`` (3x3), ``dist`` (5,)
    and ``image_size`` (w, h) are the calibrated camera (the frames are rendered *through*
    this lens model, distortion included); ``target_ct`` the 80 mm deep target (CT mm) at
    which the benchmark measures the pose error."""

    split: str
    kind: str
    index: int
    seed: int
    fiducials_ct: tuple
    radius_mm: float
    ball_finish: str
    ball_rgb: tuple
    T_cam_ct: tuple
    K: tuple
    dist: tuple
    image_size: tuple
    target_ct: tuple
    skin: Skin
    lamps: tuple
    ambient_rgb: tuple
    drapes: tuple               # panel colour names of the sheet behind the head
    towel: str                  # colour name of the towel round the head
    drape_seed: int
    fingers: tuple = ()
    rods: tuple = ()
    strays: tuple = ()
    hair_colour: str = "dark-brown"
    hair_strands: int = 300     # strands rooted outside the shaved patch
    hair_loose: int = 0         # loose strands lying across the patch
    hair_seed: int = 0
    spp: int = 64               # samples per pixel in the surgical field (field_window)
    spp_outside: int = 16       # ... and in the rest of the frame (drapes)
    renderer: str = RENDERER_VERSION

    # ---------------------------------------------------------------- derived arrays
    @property
    def T(self) -> np.ndarray:
        return np.array(self.T_cam_ct, float)

    @property
    def fiducials(self) -> np.ndarray:
        return np.array(self.fiducials_ct, float).reshape(-1, 3)

    @property
    def eye_ct(self) -> np.ndarray:
        """The camera centre in CT mm."""
        return invert_transform(self.T)[:3, 3]

    def camera_model(self):
        """The calibrated :class:`~monotracker.vision.camera_model.CameraModel` of the frames."""
        from monotracker.vision.camera_model import CameraModel

        return CameraModel(np.array(self.K, float), np.array(self.dist, float), tuple(self.image_size))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "SceneSpec":
        d = dict(d)
        d["skin"] = Skin(**d["skin"])
        d["lamps"] = tuple(Lamp(**_tuples(x)) for x in d["lamps"])
        d["fingers"] = tuple(Capsule(**_tuples(x)) for x in d.get("fingers", ()))
        d["rods"] = tuple(Rod(**_tuples(x)) for x in d.get("rods", ()))
        d["strays"] = tuple(Stray(**_tuples(x)) for x in d.get("strays", ()))
        return cls(**_tuples(d))


def _tuples(d: dict) -> dict:
    """Lists (from JSON) -> nested tuples, so a spec read back equals the one written."""

    def conv(v):
        if isinstance(v, list):
            return tuple(conv(x) for x in v)
        return v

    return {k: conv(v) for k, v in d.items()}


def _canonical(obj):
    """JSON-ready copy with floats rounded to 6 significant decimals (stable hashes)."""
    if isinstance(obj, dict):
        return {k: _canonical(v) for k, v in sorted(obj.items())}
    if isinstance(obj, (list, tuple)):
        return [_canonical(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(f"{float(obj):.6g}")
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


#: the surgical field's margin round the balls (px): rendered with the full sample count
FIELD_MARGIN_PX = 90.0


def field_window(spec: SceneSpec) -> tuple[int, int, int, int]:
    """(x, y, w, h) px of the frame round every ball (its image plus ``FIELD_MARGIN_PX``), even
    offsets and sizes (a crop keeps the full sensor's Bayer phase), inside the frame."""
    import cv2

    T = spec.T
    Xc = spec.fiducials @ T[:3, :3].T + T[:3, 3]
    px, _ = cv2.projectPoints(Xc, np.zeros(3), np.zeros(3), np.array(spec.K, float), np.array(spec.dist, float))
    px = px.reshape(-1, 2)
    r = spec.K[0][0] * spec.radius_mm / Xc[:, 2]
    lo = np.min(px - r[:, None], axis=0) - FIELD_MARGIN_PX
    hi = np.max(px + r[:, None], axis=0) + FIELD_MARGIN_PX
    W, H = spec.image_size
    x0, y0 = (max(0, int(np.floor(v / 2)) * 2) for v in lo)
    x1, y1 = min(W, int(np.ceil(hi[0] / 2)) * 2), min(H, int(np.ceil(hi[1] / 2)) * 2)
    return x0, y0, x1 - x0, y1 - y0


def scene_hash(spec: SceneSpec) -> str:
    """16 hex digits naming the render of ``spec`` (its canonical JSON, renderer version
    included): the cache key."""
    text = json.dumps(_canonical(spec.to_dict()), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def spec_json(spec: SceneSpec) -> dict:
    """The spec as written next to its render (canonical rounding)."""
    return _canonical(spec.to_dict())


# --------------------------------------------------------------------------- generation
def _t(a) -> tuple:
    return tuple(np.asarray(a, float).round(9).tolist())


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _perp_frame(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([0.0, 0.0, 1.0]) if abs(v[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = _unit(np.cross(v, helper))
    return e1, np.cross(v, e1)


def _tilted(v: np.ndarray, angle_deg: float, azimuth_rad: float) -> np.ndarray:
    e1, e2 = _perp_frame(v)
    a = np.radians(angle_deg)
    return _unit(np.cos(a) * v + np.sin(a) * (np.cos(azimuth_rad) * e1 + np.sin(azimuth_rad) * e2))


def _cct_rgb(kelvin: float) -> tuple:
    """Linear RGB of a black body of ``kelvin`` normalised to luminance 1 (Planck's law
    integrated against the CIE 1931 matching functions' Gaussian fit, then XYZ -> linear sRGB)."""
    lam = np.linspace(380e-9, 780e-9, 401)
    h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
    spd = 1.0 / (lam**5 * (np.exp(h * c / (lam * k * kelvin)) - 1.0))
    nm = lam * 1e9

    def g(x, mu, s1, s2):
        return np.exp(-0.5 * ((x - mu) / np.where(x < mu, s1, s2)) ** 2)

    xbar = 1.056 * g(nm, 599.8, 37.9, 31.0) + 0.362 * g(nm, 442.0, 16.0, 26.7) - 0.065 * g(nm, 501.1, 20.4, 26.2)
    ybar = 0.821 * g(nm, 568.8, 46.9, 40.5) + 0.286 * g(nm, 530.9, 16.3, 31.1)
    zbar = 1.217 * g(nm, 437.0, 11.8, 36.0) + 0.681 * g(nm, 459.0, 26.0, 13.8)
    X, Y, Z = (np.trapezoid(spd * b, nm) for b in (xbar, ybar, zbar))
    M = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    rgb = np.clip(M @ (np.array([X, Y, Z]) / Y), 0.0, None)
    return _t(rgb)


def _skin(family: str, rng: np.random.Generator) -> Skin:
    if family == "T":     # train: broad, chosen up front (sRGB pale to dark, satin to shiny)
        base = srgb_to_linear(np.array((235, 190, 160)) * rng.uniform(0.35, 1.05)
                              * rng.uniform(0.9, 1.1, size=3))
        return Skin("T", _t(base), float(rng.uniform(0.2, 0.75)), float(rng.uniform(0.2, 0.7)),
                    int(rng.integers(1 << 30)))
    if family == "A":     # light, freckled, satin
        base = srgb_to_linear(np.array((226, 182, 152)) * rng.uniform(0.93, 1.04))
        return Skin("A", _t(base), float(rng.uniform(0.45, 0.6)), float(rng.uniform(0.3, 0.45)),
                    int(rng.integers(1 << 30)))
    base = srgb_to_linear(np.array((176, 128, 94)) * rng.uniform(0.9, 1.05))   # B: olive-brown, shinier
    return Skin("B", _t(base), float(rng.uniform(0.3, 0.42)), float(rng.uniform(0.45, 0.6)),
                int(rng.integers(1 << 30)))


def _lamps(family: str, v: np.ndarray, centroid: np.ndarray, view_dir: np.ndarray,
           rng: np.random.Generator) -> tuple[tuple, tuple]:
    """(lamps, ambient RGB) of one scene: family A one warm lamp, B two lamps + more ambient.
    A lamp is never within 8 deg of the camera's viewing direction (no coaxial light)."""
    if family == "T":   # train: 1-3 lamps, 2700-6500 K, shares 0.3-1.0 (broad, chosen up front)
        specs = [(float(rng.uniform(2700.0, 6500.0)), float(rng.uniform(0.3, 1.0)))
                 for _ in range(int(rng.integers(1, 4)))]
    else:
        specs = [(4300.0, 1.0)] if family == "A" else [(5000.0, 0.65), (4000.0, 0.45)]
    lamps = []
    for kelvin, share in specs:
        for _ in range(100):
            d = _tilted(v, rng.uniform(10.0, 45.0), rng.uniform(0, 2 * np.pi))
            if np.degrees(np.arccos(np.clip(d @ view_dir, -1, 1))) > 8.0:
                break
        dist = rng.uniform(900.0, 1300.0)
        lamps.append(Lamp(_t(centroid + dist * d), _t(-d), float(rng.uniform(200.0, 350.0)), _cct_rgb(kelvin),
                          float(share)))
    if family == "T":   # ambient 0.01-0.2, any tint from warm to cool
        amb = rng.uniform(0.01, 0.2)
        tint = np.array(_cct_rgb(float(rng.uniform(2700.0, 8000.0))))
    else:
        amb = rng.uniform(0.03, 0.06) if family == "A" else rng.uniform(0.08, 0.14)
        tint = np.array([1.0, 0.97, 0.92]) if family == "A" else np.array([0.92, 0.97, 1.0])
    return tuple(lamps), _t(amb * tint)


def _camera(rng: np.random.Generator, X: np.ndarray, v: np.ndarray, phantom: HeadPhantom, K: np.ndarray,
            dist: np.ndarray, size: tuple, radius_mm: float, accept=None) -> np.ndarray:
    """T_cam_ct: 300-800 mm from the centroid, up to 45 deg off ``v``, any roll, centroid in the
    central half of the image, every ball's centre projected >= 40 px inside the frame; and, when
    ``accept`` is given, ``accept(X, T_cam_ct)`` true (e.g. a placement planner's verdict)."""
    import cv2

    centroid = X.mean(axis=0)
    W, H = size
    for _ in range(5000 if accept is not None else 2000):
        d = _tilted(v, 45.0 * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi))
        distance = rng.uniform(300.0, 800.0)
        eye = centroid + distance * d
        up = rotation_about_axis(d, rng.uniform(-np.pi, np.pi)) @ _perp_frame(d)[0]
        T = invert_transform(look_at(eye, centroid, up))
        # turn the camera so that the centroid lands at a random place in the central half
        want = np.array([rng.uniform(0.25, 0.75) * W, rng.uniform(0.25, 0.75) * H])
        ray = _unit(np.linalg.solve(K, [want[0], want[1], 1.0]))
        zc = _unit(T[:3, :3] @ centroid + T[:3, 3])
        axis = np.cross(zc, ray)
        if np.linalg.norm(axis) > 1e-12:
            Rs = rotation_about_axis(axis, np.arctan2(np.linalg.norm(axis), zc @ ray))
            T = np.block([[Rs, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]) @ T
        Xc = X @ T[:3, :3].T + T[:3, 3]
        if np.any(Xc[:, 2] < 150.0):
            continue
        px, _ = cv2.projectPoints(Xc, np.zeros(3), np.zeros(3), K, dist)
        px = px.reshape(-1, 2)
        r_px = K[0, 0] * radius_mm / Xc[:, 2]
        m = 40.0 + r_px
        if np.all((px[:, 0] > m) & (px[:, 0] < W - 1 - m) & (px[:, 1] > m) & (px[:, 1] < H - 1 - m)):
            if accept is None or accept(X, T):
                return T
    raise RuntimeError("could not place the camera")


def _over_ball(rng, ball: np.ndarray, eye: np.ndarray, lift_mm: tuple, reach_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """A point between ``ball`` and the camera, ``lift_mm`` (range) towards the eye and moved
    sideways (perpendicular to the line of sight) by up to ``reach_mm``; and that sideways
    unit vector (the occluder extends that way, away from the ball)."""
    los = _unit(eye - ball)
    e1, e2 = _perp_frame(los)
    a = rng.uniform(0, 2 * np.pi)
    side = np.cos(a) * e1 + np.sin(a) * e2
    p = ball + rng.uniform(*lift_mm) * los + rng.uniform(-0.3, 1.0) * reach_mm * side
    return p, side


def _fingers(rng, X, eye, kind) -> tuple:
    n = int(rng.integers(1, 3))
    gloves = ("latex", "nitrile", "brown") + (("green",) if kind == "clutter" else ())
    glove = str(rng.choice(gloves))
    j = int(rng.integers(len(X)))
    out = []
    tip, side = _over_ball(rng, X[j], eye, (18.0, 40.0), 13.0)
    los = _unit(eye - X[j])
    direction = _unit(side + rng.uniform(0.1, 0.5) * los)
    radius = float(rng.uniform(7.5, 9.5))
    for k in range(n):
        # a second finger beside the first (middle finger), a little longer
        off = np.cross(direction, los)
        off = _unit(off) * (2.05 * radius) * k
        out.append(Capsule(_t(tip + off - 6.0 * k * direction), _t(direction), radius, float(rng.uniform(70, 90)),
                           glove))
    return tuple(out)


def _rods(rng, X, eye) -> tuple:
    j = int(rng.integers(len(X)))
    mid, side = _over_ball(rng, X[j], eye, (12.0, 35.0), 6.0)
    los = _unit(eye - X[j])
    a = rng.uniform(0, 2 * np.pi)
    e1, e2 = _perp_frame(los)
    along = _unit(np.cos(a) * e1 + np.sin(a) * e2 + 0.2 * los)
    half = rng.uniform(60.0, 110.0)
    return (Rod(_t(mid - half * along), _t(mid + half * along), float(rng.uniform(1.5, 2.5)),
                float(rng.uniform(0.05, 0.2))),)


def _strays(rng, X, phantom: HeadPhantom, v: np.ndarray) -> tuple:
    shapes = ["sticker", "cap", "ball", "led"]
    rng.shuffle(shapes)
    out = []
    for shape in shapes[: int(rng.integers(2, 5))]:
        for _ in range(200):
            d = _tilted(v, rng.uniform(20.0, 50.0), rng.uniform(0, 2 * np.pi))
            p, n = phantom.skin_point(d)
            if np.min(np.linalg.norm(X - p, axis=1)) > 14.0:
                break
        if shape == "sticker":
            out.append(Stray("sticker", _t(p + 0.15 * n), _t(n), float(rng.uniform(4.0, 6.0))))
        elif shape == "cap":
            e1, _ = _perp_frame(n)
            r = float(rng.uniform(3.5, 5.0))
            out.append(Stray("cap", _t(p + (r + 0.2) * n), _t(e1), r, float(rng.uniform(14.0, 24.0))))
        elif shape == "ball":
            r = float(rng.uniform(5.5, 7.0))
            out.append(Stray("ball", _t(p + r * n), _t(n), r))
        else:
            out.append(Stray("led", _t(p + rng.uniform(15.0, 40.0) * n), _t(n), float(rng.uniform(1.5, 2.5))))
    return tuple(out)


def make_spec(split: str, kind: str, index: int, phantom: HeadPhantom | None = None,
              camera_accept=None, layout: np.ndarray | None = None,
              T_cam_ct: np.ndarray | None = None) -> SceneSpec:
    """Scene ``index`` of ``kind`` in ``split`` (see the module docstring). Deterministic.
    ``camera_accept``: None, or ``f(fiducials_ct (n, 3) mm, T_cam_ct) -> bool``: camera poses
    are drawn from the same distribution until it accepts one (a placement the layout planner
    would approve: ``scripts/render_planned.py``; the caller picks an index range of its own).
    ``layout`` (n, 3) CT mm ball centres and ``T_cam_ct`` (4, 4): given instead of drawn (a
    layout and camera the planner chose: ``render_planned.py --plan-balls``); everything else
    (lamps, skin, drapes, occluders, hair) is drawn as for any scene."""
    from monotracker.sim.scenes import head_like_layout
    from monotracker.vision.camera_model import default_camera

    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    ph = phantom or default_phantom()
    seed = SPLIT_SEED0[split] + 1000 * KINDS.index(kind) + int(index)
    rng = np.random.default_rng(seed)
    fam = FAMILIES[split]
    v = _unit(ph.view_direction_lps)
    if rng.uniform() < 0.4:
        X = ph.fiducial_centres_lps
    else:
        X = head_like_layout(rng, int(rng.integers(7, 10)), max_angle_deg=40.0)
    if layout is not None:
        X = np.asarray(layout, float).reshape(-1, 3)
    R = ph.fiducial_radius_mm
    cam = default_camera()
    if T_cam_ct is not None:
        T = np.asarray(T_cam_ct, float).reshape(4, 4)
    else:
        T = _camera(rng, X, v, ph, cam.K, cam.dist, cam.image_size, R, camera_accept)
    eye = invert_transform(T)[:3, 3]
    centroid = X.mean(axis=0)
    view_dir = _unit(eye - centroid)
    lamps, ambient = _lamps(fam["lamps"], v, centroid, view_dir, rng)
    finish = "glossy" if rng.uniform() < 0.5 else "matte"
    ball_rgb = np.array(BALL_RGB) * rng.uniform(0.9, 1.1)
    palette = ["blue", "light-blue", "teal", "or-green", "green-blue"]
    drapes = tuple(str(c) for c in rng.choice(palette, size=int(rng.integers(2, 4)), replace=False))
    towel = str(rng.choice(palette))
    kw = {}
    if kind in ("OR", "clutter"):
        kw["fingers"] = _fingers(rng, X, eye, kind)
        kw["rods"] = _rods(rng, X, eye)
    if kind == "clutter":
        kw["strays"] = _strays(rng, X, ph, v)
    hair = {"clean": (300, 0), "OR": (700, 8), "clutter": (1500, 60)}[kind]
    return SceneSpec(
        split=split, kind=kind, index=int(index), seed=seed, fiducials_ct=_t(X), radius_mm=float(R),
        ball_finish=finish, ball_rgb=_t(ball_rgb), T_cam_ct=_t(T), K=_t(cam.K), dist=_t(cam.dist),
        image_size=tuple(int(s) for s in cam.image_size), target_ct=_t(centroid - 80.0 * v),
        skin=_skin(fam["skin"], rng), lamps=lamps, ambient_rgb=ambient, drapes=drapes, towel=towel,
        drape_seed=int(rng.integers(1 << 30)), hair_colour=str(rng.choice(fam["hair"])), hair_strands=hair[0],
        hair_loose=hair[1], hair_seed=int(rng.integers(1 << 30)), **kw)


#: camera optics other than the generator's own (1280 x 720, f = 1100 px), for a measurement of
#: the camera path on lenses and sensors it was never tuned for (``with_optics``;
#: ``scripts/render_planned.py --optics``): name -> (image size (w, h) px, the intrinsics' scale
#: (fx, fy, cx, cy multiplied), a focal length (px) that replaces fx and fy, or None).
#: ``hd``: the same view on a 1920 x 1080 sensor (every length in px x 1.5, balls 1.5x larger);
#: ``wide``: a shorter lens on the same sensor (f = 800 px: balls 0.73x, the view wider, more of
#: the lens' distortion used towards the corners). Chosen 2026-12-03 before any render.
OPTICS = {
    "native": None,
    "hd": ((1920, 1080), 1.5, None),
    "wide": ((1280, 720), 1.0, 800.0),
}


def with_optics(spec: SceneSpec, name: str) -> SceneSpec:
    """``spec`` seen through camera optics ``name`` (:data:`OPTICS`): the same scene, the same
    camera pose and distortion coefficients (in normalised coordinates), another sensor size or
    focal length. ``native`` returns ``spec`` itself; any other name a scene with its own hash."""
    if _optics(name) is None:
        return spec
    K, size = _optics_intrinsics(np.array(spec.K, float), name)
    return replace(spec, K=tuple([float(v) for v in row] for row in K), image_size=size)


def optics_camera(name: str):
    """The generator's camera (:func:`~monotracker.vision.camera_model.default_camera`) through
    optics ``name`` (:data:`OPTICS`): what a layout planned for that camera must be given
    (``render_planned.py --plan-balls N --optics NAME`` plans for it)."""
    from monotracker.vision.camera_model import CameraModel, default_camera

    cam = default_camera()
    if _optics(name) is None:
        return cam
    K, size = _optics_intrinsics(np.array(cam.K, float), name)
    return CameraModel(K, cam.dist, size)


def _optics(name: str):
    if name not in OPTICS:
        raise ValueError(f"optics must be one of {', '.join(OPTICS)}, got {name!r}")
    return OPTICS[name]


def _optics_intrinsics(K: np.ndarray, name: str) -> tuple[np.ndarray, tuple]:
    """(K (3, 3) px, image size (w, h) px) of the native ``K`` through optics ``name``."""
    size, scale, focal = OPTICS[name]
    K = K.copy()
    K[:2, :] *= scale
    if focal is not None:
        K[0, 0] = K[1, 1] = focal
    return K, tuple(int(s) for s in size)


@dataclass
class SetPlan:
    """How many scenes of each kind a frame set holds."""

    split: str
    counts: dict = field(default_factory=lambda: {"clean": 20, "OR": 20, "clutter": 20})

    def specs(self) -> list[SceneSpec]:
        return [make_spec(self.split, k, i) for k in KINDS for i in range(self.counts.get(k, 0))]
