"""Render a :class:`~.spec.SceneSpec` with Mitsuba 3 (a physically based path tracer nobody on
this project wrote) and ray-cast each ball's visibility against the same scene.

Optional dependency: ``pip install -e '.[render]'`` and Debian's ``libllvm19`` (Mitsuba's
``llvm_ad_rgb`` variant JIT-compiles with it; LLVM 14/15 crash it). :func:`load_mitsuba` says in
one line what is missing. Nothing else in the package imports this module: the tests and the
benchmarks read rendered frames from disk (:mod:`.frameset`).

* **Camera**: a Mitsuba sensor written here in Python (:class:`_OpenCVSensor`) that traces, for
  every point of every pixel, the ray the calibrated lens model (OpenCV's K and k1, k2, p1, p2,
  k3) assigns to it: distortion is rendered, not resampled afterwards, and the box pixel filter
  integrates each pixel's area as a sensor does. Pixel centres at integer coordinates (OpenCV).
* **Light transport**: ``path`` integrator (6 bounces: inter-reflections between skin, balls and
  gloves), area lights (round OR lamps), a constant ambient, soft and contact shadows as they fall.
* **Materials**: skin = ``principled`` (textured albedo, GGX roughness, dielectric specular; no
  sub-surface scattering: Mitsuba 3 ships none), balls = ``roughplastic`` (matte, alpha 0.35) or
  ``plastic`` (glossy, a smooth coat), gloves = ``roughplastic``, steel = ``roughconductor``
  (chromium), drapes = ``diffuse`` textured fabric, hair = ``diffuse`` curves, strays = the balls'
  green (an LED emits).
* **Output**: linear RGB radiance (float32, (h, w, 3)), then a camera's exposure metered on the
  fiducials' neighbourhood (:func:`auto_exposure`) -> sRGB 8-bit (:func:`encode_srgb`).
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

from monotracker.errors import InputError

from .spec import GLOVE_RGB, HAIR_RGB, SceneSpec, _perp_frame, _unit
from .surfaces import (HAIR_RADIUS_MM, drape_sheet, drape_texture, hair_curves, head_mesh, plain_texture,
                       skin_texture, towel_band)
from .truth import visibility_rays

VARIANT = "llvm_ad_rgb"
_LLVM_CANDIDATES = ("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1", "/usr/lib/x86_64-linux-gnu/libLLVM-19.so")
_MI = None


def load_mitsuba():
    """Import Mitsuba 3 with the ``llvm_ad_rgb`` variant and register our camera; raises
    :class:`InputError` (one line) when it cannot."""
    global _MI
    if _MI is not None:
        return _MI
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        for p in _LLVM_CANDIDATES:
            if os.path.exists(p):
                os.environ["DRJIT_LIBLLVM_PATH"] = p
                break
    try:
        import mitsuba as mi
    except ImportError as exc:
        raise InputError("the physically based renderer needs Mitsuba 3: pip install -e '.[render]' "
                         f"(and apt-get install libllvm19) ({exc})") from None
    try:
        mi.set_variant(VARIANT)
    except Exception as exc:  # noqa: BLE001 - one line for the operator
        raise InputError(f"Mitsuba's {VARIANT} variant does not load ({exc}); install Debian's libllvm19 and set "
                         "DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") from None
    import drjit as dr

    # one CPU slot = one core (COORDINATION: renders hold one slot): MONOTRACKER_RENDER_THREADS
    dr.set_thread_count(int(os.environ.get("MONOTRACKER_RENDER_THREADS", "1")))
    _register_sensor(mi)
    _MI = mi
    return mi


def _register_sensor(mi) -> None:
    import drjit as dr

    class _OpenCVSensor(mi.Sensor):
        """Pinhole camera with OpenCV's lens distortion: film point -> distorted pixel ->
        undistorted normalised coordinates (fixed-point iteration, as cv2.undistortPoints) ->
        ray. Properties: fx, fy, cx, cy (px, integer pixel centres), k1, k2, p1, p2, k3,
        to_world (the camera's pose; OpenCV axes: x right, y down, z forward)."""

        def __init__(self, props):
            super().__init__(props)
            self.fx, self.fy = props.get("fx"), props.get("fy")
            self.cx, self.cy = props.get("cx"), props.get("cy")
            self.k = [props.get(n, 0.0) for n in ("k1", "k2", "p1", "p2", "k3")]
            # the integrator's sample position spans the film's crop window (the whole film
            # when not cropped): film px = crop offset + position * crop size
            off, size = self.film().crop_offset(), self.film().crop_size()
            self.x0, self.y0 = float(off[0]), float(off[1])
            self.w, self.h = float(size[0]), float(size[1])
            M = np.array(props.get("to_world_cv").matrix, dtype=float)
            self.R, self.o = M[:3, :3], M[:3, 3]

        def _direction(self, pos):
            u = self.x0 + pos.x * self.w - 0.5
            v = self.y0 + pos.y * self.h - 0.5
            xd = (u - self.cx) / self.fx
            yd = (v - self.cy) / self.fy
            k1, k2, p1, p2, k3 = self.k
            x, y = mi.Float(xd), mi.Float(yd)
            for _ in range(12):
                r2 = x * x + y * y
                radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
                dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
                x = (xd - dx) / radial
                y = (yd - dy) / radial
            return dr.normalize(mi.Vector3f(x, y, 1.0))

        def sample_ray(self, time, sample1, sample2, sample3, active=True):
            d = self._direction(sample2)
            R = self.R
            dw = mi.Vector3f(*(float(R[i, 0]) * d.x + float(R[i, 1]) * d.y + float(R[i, 2]) * d.z for i in range(3)))
            o = mi.Point3f(*(float(v) for v in self.o))
            return mi.Ray3f(o, dw, time, []), mi.Color3f(1.0)

        def sample_ray_differential(self, time, sample1, sample2, sample3, active=True):
            ray, w = self.sample_ray(time, sample1, sample2, sample3, active)
            return mi.RayDifferential3f(ray), w

        def bbox(self):
            return mi.ScalarBoundingBox3f()

        def to_string(self):
            return "OpenCVSensor[]"

    mi.register_sensor("opencv_camera", lambda props: _OpenCVSensor(props))


# --------------------------------------------------------------------------- scene assembly
def _write_ply(path: Path, V: np.ndarray, N: np.ndarray, uv: np.ndarray, F: np.ndarray) -> None:
    vert = np.empty(len(V), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"),
                                   ("nz", "<f4"), ("u", "<f4"), ("v", "<f4")])
    for k, name in enumerate("xyz"):
        vert[name] = V[:, k]
    for k, name in enumerate(("nx", "ny", "nz")):
        vert[name] = N[:, k]
    vert["u"], vert["v"] = uv[:, 0], uv[:, 1]
    faces = np.empty(len(F), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = F
    head = ("ply\nformat binary_little_endian 1.0\n"
            f"element vertex {len(V)}\n" + "".join(f"property float {n}\n" for n in vert.dtype.names)
            + f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as f:
        f.write(head.encode())
        f.write(vert.tobytes())
        f.write(faces.tobytes())


def _transform(mi, M: np.ndarray):
    return mi.ScalarTransform4f(np.asarray(M, float).tolist())


def _frame_to(z: np.ndarray) -> np.ndarray:
    """3x3 rotation taking +z to unit ``z``."""
    z = _unit(z)
    x, y = _perp_frame(z)
    return np.column_stack([x, y, z])


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(v) for v in value]}


def _capsule(mi, name: str, a: np.ndarray, b: np.ndarray, r: float, bsdf: dict) -> dict:
    """A cylinder from a to b closed by spheres at both ends (radius r, mm)."""
    return {f"{name}_body": {"type": "cylinder", "p0": a.tolist(), "p1": b.tolist(), "radius": float(r), "bsdf": bsdf},
            f"{name}_end0": {"type": "sphere", "center": a.tolist(), "radius": r, "bsdf": bsdf},
            f"{name}_end1": {"type": "sphere", "center": b.tolist(), "radius": r, "bsdf": bsdf}}


def ball_shape_names(spec: SceneSpec) -> list[str]:
    return [f"ball{j:02d}" for j in range(len(spec.fiducials))]


def scene_dict(spec: SceneSpec, workdir: Path, window: tuple | None = None, spp: int | None = None) -> dict:
    """The Mitsuba scene dictionary of ``spec`` (meshes and curves written under ``workdir``);
    ``window`` (x, y, w, h px) renders only that part of the frame; ``spp`` overrides the
    spec's samples per pixel."""
    mi = load_mitsuba()
    from monotracker.sim.phantom import default_phantom

    ph = default_phantom()
    W, H = spec.image_size
    K = np.array(spec.K, float)
    dist = list(spec.dist) + [0.0] * (5 - len(spec.dist))
    T_ct_cam = np.linalg.inv(spec.T)
    sc: dict = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 6},
        "sensor": {"type": "opencv_camera", "fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]),
                   "cy": float(K[1, 2]), "k1": float(dist[0]), "k2": float(dist[1]), "p1": float(dist[2]),
                   "p2": float(dist[3]), "k3": float(dist[4]), "to_world_cv": _transform(mi, T_ct_cam),
                   "film": {"type": "hdrfilm", "width": int(W), "height": int(H), "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": int(spp or spec.spp)}},
        "ambient": {"type": "constant", "radiance": _rgb(spec.ambient_rgb)},
    }
    if window is not None:
        x, y, w, h = (int(v) for v in window)
        sc["sensor"]["film"].update(crop_offset_x=x, crop_offset_y=y, crop_width=w, crop_height=h)
    # skin
    V, N, uv, F = head_mesh(ph)
    _write_ply(workdir / "head.ply", V, N, uv, F)
    sc["head"] = {"type": "ply", "filename": str(workdir / "head.ply"), "face_normals": False,
                  "bsdf": {"type": "principled",
                           "base_color": {"type": "bitmap", "bitmap": mi.Bitmap(skin_texture(spec)),
                                          "filter_type": "bilinear", "wrap_mode": "repeat"},
                           "roughness": float(spec.skin.roughness), "specular": float(spec.skin.specular)}}
    # drapes
    M, normals = drape_sheet(ph, spec.drape_seed)
    sc["sheet"] = {"type": "rectangle", "to_world": _transform(mi, M),
                   "bsdf": {"type": "normalmap",
                            "normalmap": {"type": "bitmap", "raw": True, "bitmap": mi.Bitmap(normals),
                                          "filter_type": "bilinear"},
                            "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(
                                drape_texture(spec.drapes, spec.drape_seed)), "filter_type": "bilinear"}}}}
    V, N, uv, F = towel_band(ph, spec.drape_seed)
    _write_ply(workdir / "towel.ply", V, N, uv, F)
    sc["towel"] = {"type": "ply", "filename": str(workdir / "towel.ply"),
                   "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {
                       "type": "bitmap", "bitmap": mi.Bitmap(plain_texture(spec.towel, spec.drape_seed)),
                       "filter_type": "bilinear", "wrap_mode": "repeat"}}}}
    # balls
    if spec.ball_finish == "glossy":
        ball_bsdf = {"type": "plastic", "diffuse_reflectance": _rgb(spec.ball_rgb), "int_ior": 1.5}
    else:
        ball_bsdf = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.35,
                     "diffuse_reflectance": _rgb(spec.ball_rgb), "int_ior": 1.5}
    for name, c in zip(ball_shape_names(spec), spec.fiducials):
        sc[name] = {"type": "sphere", "center": c.tolist(), "radius": float(spec.radius_mm), "bsdf": ball_bsdf}
    # lamps
    for k, lamp in enumerate(spec.lamps):
        M = np.eye(4)
        M[:3, :3] = _frame_to(np.array(lamp.normal)) * lamp.radius_mm
        M[:3, 3] = lamp.centre
        area = np.pi * lamp.radius_mm**2
        d2 = float(np.sum((np.array(lamp.centre) - spec.fiducials.mean(0)) ** 2))
        radiance = np.array(lamp.rgb) * lamp.irradiance * d2 / area     # irradiance ~ L A / d^2 at the patch
        sc[f"lamp{k}"] = {"type": "disk", "to_world": _transform(mi, M),
                          "emitter": {"type": "area", "radiance": _rgb(radiance)}}
    # gloved fingers, steel, strays
    for k, f in enumerate(spec.fingers):
        tip = np.array(f.tip)
        bsdf = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.3,
                "diffuse_reflectance": _rgb(GLOVE_RGB[f.glove]), "int_ior": 1.45}
        sc.update(_capsule(mi, f"finger{k}", tip, tip + f.length_mm * np.array(f.direction), f.radius_mm, bsdf))
    for k, r in enumerate(spec.rods):
        bsdf = {"type": "roughconductor", "material": "Cr", "distribution": "ggx", "alpha": float(r.roughness)}
        sc.update(_capsule(mi, f"rod{k}", np.array(r.start), np.array(r.end), r.radius_mm, bsdf))
    green = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.3, "diffuse_reflectance": _rgb(spec.ball_rgb),
             "int_ior": 1.5}
    for k, s in enumerate(spec.strays):
        c, ax = np.array(s.centre), np.array(s.axis)
        if s.shape == "sticker":
            M = np.eye(4)
            M[:3, :3] = _frame_to(ax) * s.size_mm
            M[:3, 3] = c
            sc[f"stray{k}"] = {"type": "disk", "to_world": _transform(mi, M), "bsdf": {"type": "twosided",
                                                                                     "bsdf": green}}
        elif s.shape == "cap":
            sc.update(_capsule(mi, f"stray{k}", c - 0.5 * s.length_mm * ax, c + 0.5 * s.length_mm * ax, s.size_mm,
                               green))
        elif s.shape == "ball":
            sc[f"stray{k}"] = {"type": "sphere", "center": c.tolist(), "radius": s.size_mm, "bsdf": green}
        else:
            sc[f"stray{k}"] = {"type": "sphere", "center": c.tolist(), "radius": s.size_mm,
                               "emitter": {"type": "area", "radiance": _rgb([0.3, 6.0, 0.5])}}
    # hair
    strands = hair_curves(spec, ph)
    if strands:
        path = workdir / "hair.txt"
        with open(path, "w") as fh:
            for s in strands:
                for p in s:
                    fh.write(f"{p[0]:.5f} {p[1]:.5f} {p[2]:.5f} {HAIR_RADIUS_MM}\n")
                fh.write("\n")
        sc["hair"] = {"type": "linearcurve", "filename": str(path),
                      "bsdf": {"type": "diffuse", "reflectance": _rgb(HAIR_RGB[spec.hair_colour])}}
    return sc


def coverage_dict(spec: SceneSpec, workdir: Path, window: tuple | None = None) -> dict:
    """The same geometry as :func:`scene_dict` with every ball an emitter of radiance 1 and
    everything else black, no lights: rendered with camera rays only (``max_depth`` 1) it is
    each pixel's visible ball coverage (0-1; the box filter integrates the pixel's area),
    occluders, hair and the frame's edge included."""
    sc = scene_dict(spec, workdir, window)
    black = {"type": "diffuse", "reflectance": _rgb([0.0, 0.0, 0.0])}
    out = {"type": "scene", "integrator": {"type": "path", "max_depth": 1},
           "sensor": sc["sensor"]}
    balls = set(ball_shape_names(spec))
    for k, v in sc.items():
        if k in ("type", "integrator", "sensor", "ambient") or k.startswith("lamp"):
            continue
        v = dict(v)
        v.pop("emitter", None)
        if k in balls:
            v.pop("bsdf", None)
            v["emitter"] = {"type": "area", "radiance": _rgb([1.0, 1.0, 1.0])}
        else:
            v["bsdf"] = black
        out[k] = v
    return out


# --------------------------------------------------------------------------- render + truth
def render_linear(spec: SceneSpec, seed: int | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Render ``spec``: (linear RGB float32 (h, w, 3), visible ball coverage float32 (h, w) in
    [0, 1] (:func:`coverage_dict`), info: seconds, spp, variant, mitsuba version, visible
    fraction per ball (ray-cast, see :func:`visible_fractions`)). The surgical field (the
    balls' neighbourhood, :func:`~.spec.field_window`) gets ``spec.spp`` samples per pixel, the
    rest of the frame (drapes) ``spec.spp_outside``."""
    from .spec import field_window

    mi = load_mitsuba()
    seed = int(spec.seed if seed is None else seed)
    W, H = spec.image_size
    x, y, w, h = field_window(spec)
    with tempfile.TemporaryDirectory(prefix="mt_pbr_") as tmp:
        t0 = time.perf_counter()
        scene = mi.load_dict(scene_dict(spec, Path(tmp), spp=spec.spp_outside))
        field = mi.load_dict(scene_dict(spec, Path(tmp), (x, y, w, h)))
        t_load = time.perf_counter() - t0
        img = _render_passes(mi, scene, seed, int(spec.spp_outside))
        img[y:y + h, x:x + w] = _render_passes(mi, field, seed + 1, int(spec.spp))
        t_render = time.perf_counter() - t0 - t_load
        vis = visible_fractions(spec, scene)
        cov = np.zeros((H, W), np.float32)
        cov[y:y + h, x:x + w] = _render_passes(mi, mi.load_dict(coverage_dict(spec, Path(tmp), (x, y, w, h))), seed + 7,
                                               int(spec.spp))[..., 1]
    info = {"variant": VARIANT, "mitsuba": mi.__version__, "spp": int(spec.spp), "spp_outside": int(spec.spp_outside),
            "field_window": [int(v) for v in (x, y, w, h)], "threads": _threads(), "load_s": round(t_load, 2),
            "render_s": round(t_render, 2), "visible_fraction": [round(float(v), 4) for v in vis]}
    return img[..., :3], np.clip(cov, 0.0, 1.0), info


def _threads() -> int:
    import drjit as dr

    return int(dr.thread_count())


#: samples per pixel per render pass (a 64 spp frame in one pass holds ~59 M paths' state at once)
SPP_PER_PASS = 16


def _render_passes(mi, scene, seed: int, spp: int) -> np.ndarray:
    """Mean of ``spp / SPP_PER_PASS`` independent passes (independent sampler, distinct seeds):
    the same estimator as one pass of ``spp`` samples, in bounded memory."""
    passes = max(1, int(np.ceil(spp / SPP_PER_PASS)))
    acc = None
    for k in range(passes):
        img = np.array(mi.render(scene, seed=seed * 64 + k, spp=min(SPP_PER_PASS, spp)), dtype=np.float32)
        acc = img if acc is None else acc + img
    return acc / passes


def visible_fractions(spec: SceneSpec, scene, n: int = 2048) -> np.ndarray:
    """Per ball, the share of its silhouette that the camera sees inside the frame
    (:func:`~.truth.visibility_rays`: ``n`` rays per ball spread evenly over the cone tangent to
    the sphere) intersected with the whole scene by Mitsuba (``scene.ray_intersect``); a ray
    counts when its first hit is the ball (within 0.01 mm of the ray's analytic entry into the
    sphere) and its pixel lies in the image."""
    mi = load_mitsuba()
    out = []
    for rays in visibility_rays(spec, n):
        eye, d_ct = rays.origin_ct, rays.directions_ct
        mrays = mi.Ray3f(mi.Point3f(*[np.full(len(d_ct), v, np.float32) for v in eye]),
                         mi.Vector3f(*[d_ct[:, k].astype(np.float32) for k in range(3)]))
        si = scene.ray_intersect(mrays)
        t_hit = np.array(si.t, dtype=np.float64)
        hit_ball = np.abs(t_hit - rays.t_entry) < 0.01
        out.append(float(np.mean(hit_ball & rays.counts)))
    return np.array(out)


def auto_exposure(linear: np.ndarray, box: tuple, target: float = 0.3) -> float:
    """A camera's exposure gain, metered on the surgical field as an OR camera is set up: the
    median luminance inside ``box`` (x0, y0, x1, y1 px: the fiducials' neighbourhood) -> ``target``
    (linear; skin then sits near 0.6 of the sRGB range, a glossy highlight clips)."""
    h, w = linear.shape[:2]
    x0, y0, x1, y1 = (int(round(v)) for v in box)
    c = linear[max(0, y0):min(h, y1), max(0, x0):min(w, x1)]
    if c.size == 0:
        c = linear
    lum = 0.2126 * c[..., 0] + 0.7152 * c[..., 1] + 0.0722 * c[..., 2]
    med = float(np.median(lum))
    return target / med if med > 1e-9 else 1.0


def encode_srgb(linear_rgb: np.ndarray) -> np.ndarray:
    """Linear RGB (exposed, 1.0 = white) -> 8-bit BGR with the sRGB curve (clips highlights)."""
    c = np.clip(linear_rgb, 0.0, 1.0)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)
    return (s[..., ::-1] * 255.0 + 0.5).astype(np.uint8)
