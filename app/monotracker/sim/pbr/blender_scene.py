"""Build and render a scene package (:func:`.blender_render.export_package`) with Blender's Cycles.

Runs in a Python that has the ``bpy`` wheel (never the project's own environment; it imports
only ``bpy`` and ``numpy``, not ``monotracker``)::

    /work/bpyenv/bin/python blender_scene.py PACKAGE/scene.json OUT_DIR [--threads 1]

Writes ``OUT_DIR/linear.npy`` (float32 (h, w, 3): linear Rec.709 radiance, the surgical field
rendered with ``spp`` samples per pixel, the rest with ``spp_outside``) and ``OUT_DIR/result.json``
(Blender's version, seconds, the window, and per ball for each visibility ray whether its first
hit in the scene is that ball).

Units: 1 Blender unit = 1 mm (CT LPS). The camera: OpenCV axes (x right, y down, z forward) in
``T_ct_cam``; Blender's camera looks down its -z with +y up, hence the axis flip; the focal
length and lens shift reproduce K with OpenCV's pixel centres at integer coordinates (Blender's
raster pixel i spans [i, i + 1], so its centre is OpenCV's i).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix, Vector

SENSOR_WIDTH_MM = 36.0


# ------------------------------------------------------------------------------- geometry
def _mesh_object(name: str, V: np.ndarray, faces, material, uv: np.ndarray | None = None,
                 smooth: bool = True):
    """A mesh object of vertices ``V`` (n, 3) mm and ``faces`` (index tuples, triangles or
    quads), linked to the scene, with ``material`` and optional per-vertex ``uv``."""
    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(v) for v in np.asarray(V, float)], [], [tuple(int(i) for i in f) for f in faces])
    if uv is not None:
        layer = me.uv_layers.new(name="UVMap")
        loops = np.empty(len(me.loops), np.int32)
        me.loops.foreach_get("vertex_index", loops)
        layer.data.foreach_set("uv", np.asarray(uv, np.float32)[loops].ravel())
    me.polygons.foreach_set("use_smooth", [smooth] * len(me.polygons))
    me.update()
    ob = bpy.data.objects.new(name, me)
    ob.data.materials.append(material)
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _uv_sphere(c, r, nu: int = 256, nv: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere whose facets sag < r (1 - cos(pi / nu)) (4 mm ball: 0.0003 mm)."""
    th = np.linspace(0, np.pi, nv + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(TH) * np.cos(PH), np.sin(TH) * np.sin(PH), np.cos(TH)], -1).reshape(-1, 3)
    V = np.vstack([[0, 0, 1], ring, [0, 0, -1]]) * r + np.asarray(c, float)
    faces = []
    top, bottom = 0, len(V) - 1
    for j in range(nu):
        faces.append((top, 1 + j, 1 + (j + 1) % nu))
    for i in range(nv - 2):
        for j in range(nu):
            a, b = 1 + i * nu + j, 1 + i * nu + (j + 1) % nu
            faces.append((a, a + nu, b + nu, b))
    base = 1 + (nv - 2) * nu
    for j in range(nu):
        faces.append((base + (j + 1) % nu, base + j, bottom))
    return V, faces


def _cylinder(a, b, r, n: int = 96) -> tuple[np.ndarray, list]:
    a, b = np.asarray(a, float), np.asarray(b, float)
    z = (b - a) / np.linalg.norm(b - a)
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(z, helper)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = r * (np.cos(ang)[:, None] * x + np.sin(ang)[:, None] * y)
    V = np.vstack([a + ring, b + ring])
    faces = [(j, (j + 1) % n, n + (j + 1) % n, n + j) for j in range(n)]
    return V, faces


def _add_sphere(name, c, r, material):
    return _mesh_object(name, *_uv_sphere(c, r), material)


def _add_capsule(name, a, b, r, material):
    for part, (V, F) in (("body", _cylinder(a, b, r)), ("end0", _uv_sphere(a, r, 96, 48)),
                         ("end1", _uv_sphere(b, r, 96, 48))):
        _mesh_object(f"{name}_{part}", V, F, material)


def _add_hair(points: np.ndarray, counts: np.ndarray, radius: float, material):
    cu = bpy.data.curves.new("hair", type="CURVE")
    cu.dimensions = "3D"
    cu.bevel_depth = radius
    cu.bevel_resolution = 1
    start = 0
    for n in counts:
        sp = cu.splines.new("POLY")
        sp.points.add(int(n) - 1)
        pts = np.c_[points[start:start + n], np.ones(n)].astype(np.float32)
        sp.points.foreach_set("co", pts.ravel())
        start += int(n)
    ob = bpy.data.objects.new("hair", cu)
    ob.data.materials.append(material)
    bpy.context.scene.collection.objects.link(ob)


# ------------------------------------------------------------------------------- materials
def _image(name: str, arr: np.ndarray, colour: bool):
    h, w = arr.shape[:2]
    img = bpy.data.images.new(name, w, h, float_buffer=True, alpha=True)
    img.colorspace_settings.name = "Linear Rec.709" if colour else "Non-Color"
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = arr[::-1]                   # Blender's pixel rows run bottom-up
    img.pixels.foreach_set(rgba.ravel())
    img.pack()
    return img


def _material(name: str, spec: dict, arrays) -> "bpy.types.Material":
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    out = nt.nodes["Material Output"]
    bsdf = nt.nodes["Principled BSDF"]
    kind = spec["kind"]

    def texture(key: str, colour: bool):
        node = nt.nodes.new("ShaderNodeTexImage")
        node.image = _image(key, arrays[key], colour)
        node.interpolation = "Linear"
        return node

    bsdf.inputs["Specular IOR Level"].default_value = 0.5
    if kind == "emission":
        em = nt.nodes.new("ShaderNodeEmission")
        rgb = np.asarray(spec["rgb"], float)
        em.inputs["Color"].default_value = (*(rgb / rgb.max()), 1.0)
        em.inputs["Strength"].default_value = float(rgb.max())
        nt.links.new(em.outputs["Emission"], out.inputs["Surface"])
        return mat
    if "texture" in spec:
        nt.links.new(texture(spec["texture"], True).outputs["Color"], bsdf.inputs["Base Color"])
    else:
        bsdf.inputs["Base Color"].default_value = (*spec["rgb"], 1.0)
    if spec.get("normal_map"):
        nm = nt.nodes.new("ShaderNodeNormalMap")
        nt.links.new(texture(spec["normal_map"], False).outputs["Color"], nm.inputs["Color"])
        nt.links.new(nm.outputs["Normal"], bsdf.inputs["Normal"])
    if kind == "diffuse":
        bsdf.inputs["Roughness"].default_value = 1.0
        bsdf.inputs["Specular IOR Level"].default_value = 0.0
    elif kind == "skin":
        bsdf.inputs["Roughness"].default_value = float(spec["roughness"])
        bsdf.inputs["Specular IOR Level"].default_value = float(spec["specular"])
        bsdf.subsurface_method = "RANDOM_WALK"
        bsdf.inputs["Subsurface Weight"].default_value = 1.0
        bsdf.inputs["Subsurface Radius"].default_value = tuple(spec["sss_radius"])
        bsdf.inputs["Subsurface Scale"].default_value = float(spec["sss_scale"])
    elif kind == "ball":
        if spec["finish"] == "glossy":
            bsdf.inputs["Roughness"].default_value = 0.5
            bsdf.inputs["Coat Weight"].default_value = 1.0
            bsdf.inputs["Coat Roughness"].default_value = 0.03
            bsdf.inputs["Coat IOR"].default_value = 1.5
        else:
            bsdf.inputs["Roughness"].default_value = math.sqrt(0.35)
    elif kind == "plastic":
        bsdf.inputs["Roughness"].default_value = float(spec["roughness"])
    elif kind == "metal":
        bsdf.inputs["Metallic"].default_value = 1.0
        bsdf.inputs["Roughness"].default_value = float(spec["roughness"])
    return mat


# ------------------------------------------------------------------------------- camera
def _camera(cam: dict):
    K = np.asarray(cam["K"], float)
    W, H = cam["image_size"]
    data = bpy.data.cameras.new("camera")
    data.type = "PERSP"
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = SENSOR_WIDTH_MM
    data.lens = K[0, 0] * SENSOR_WIDTH_MM / W
    # the optical axis crosses the raster at (cx + 0.5, cy + 0.5) (raster y down); Blender's
    # shift is in units of the larger image side, + moving the frame right / up
    data.shift_x = -((K[0, 2] + 0.5) - W / 2) / max(W, H)
    data.shift_y = ((K[1, 2] + 0.5) - H / 2) / max(W, H)
    data.clip_start = 1.0
    data.clip_end = 1.0e5
    ob = bpy.data.objects.new("camera", data)
    T = np.asarray(cam["T_ct_cam"], float) @ np.diag([1.0, -1.0, -1.0, 1.0])
    ob.matrix_world = Matrix(T.tolist())
    bpy.context.scene.collection.objects.link(ob)
    bpy.context.scene.camera = ob
    sc = bpy.context.scene
    sc.render.resolution_x, sc.render.resolution_y = int(W), int(H)
    sc.render.resolution_percentage = 100
    sc.render.pixel_aspect_x = sc.render.pixel_aspect_y = 1.0     # fx = fy (square pixels)
    return ob


# ------------------------------------------------------------------------------- render
def _render(out_exr: Path, spp: int, seed: int, window=None) -> np.ndarray:
    sc = bpy.context.scene
    sc.cycles.samples = int(spp)
    sc.cycles.seed = int(seed)
    W, H = sc.render.resolution_x, sc.render.resolution_y
    if window is not None:
        x, y, w, h = window
        sc.render.use_border = True
        sc.render.use_crop_to_border = False
        sc.render.border_min_x, sc.render.border_max_x = x / W, (x + w) / W
        sc.render.border_min_y, sc.render.border_max_y = 1.0 - (y + h) / H, 1.0 - y / H
    else:
        sc.render.use_border = False
    sc.render.filepath = str(out_exr)
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(str(out_exr))
    buf = np.empty(W * H * 4, np.float32)
    img.pixels.foreach_get(buf)
    bpy.data.images.remove(img)
    return buf.reshape(H, W, 4)[::-1, :, :3].copy()


def _setup(scene: dict, threads: int) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.unit_settings.system = "NONE"
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.use_adaptive_sampling = False
    sc.cycles.use_denoising = False
    sc.cycles.pixel_filter_type = "BOX"
    sc.cycles.filter_width = 1.0
    nb = int(scene["max_bounces"])
    sc.cycles.max_bounces = nb
    sc.cycles.diffuse_bounces = sc.cycles.glossy_bounces = sc.cycles.transmission_bounces = nb
    sc.cycles.sample_clamp_direct = sc.cycles.sample_clamp_indirect = 0.0
    sc.render.threads_mode = "FIXED"
    sc.render.threads = int(threads)
    sc.render.film_transparent = False
    sc.view_settings.view_transform = "Standard"
    sc.render.image_settings.file_format = "OPEN_EXR"
    sc.render.image_settings.color_depth = "32"
    sc.render.image_settings.exr_codec = "ZIP"
    world = bpy.data.worlds.new("ambient")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (*scene["ambient_rgb"], 1.0)
    bg.inputs["Strength"].default_value = 1.0
    sc.world = world


def build(scene: dict, arrays) -> None:
    mats = {name: _material(name, m, arrays) for name, m in scene["materials"].items()}
    for ob in scene["objects"]:
        m = mats[ob["material"]]
        if ob["type"] == "mesh":
            uv = arrays[f"{ob['name']}.uv"] if f"{ob['name']}.uv" in arrays else None
            _mesh_object(ob["name"], arrays[f"{ob['name']}.V"], arrays[f"{ob['name']}.F"], m, uv)
        elif ob["type"] == "sphere":
            _add_sphere(ob["name"], ob["centre"], ob["radius"], m)
        elif ob["type"] == "capsule":
            _add_capsule(ob["name"], ob["a"], ob["b"], ob["radius"], m)
    for lamp in scene["lamps"]:
        emitter = _material(lamp["name"], {"kind": "emission", "rgb": lamp["radiance"]}, arrays)
        _mesh_object(lamp["name"], arrays[f"{lamp['name']}.V"], arrays[f"{lamp['name']}.F"], emitter, smooth=False)
    if scene.get("hair"):
        _add_hair(arrays["hair.points"], arrays["hair.counts"], scene["hair"]["radius"], mats[scene["hair"]["material"]])
    _camera(scene["camera"])


def first_hits(scene: dict, arrays) -> list[list[bool]]:
    """Per ball, per visibility ray: is the first object the ray meets this ball?"""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    sc = bpy.context.scene
    origin = Vector(scene["rays"]["origin"])
    out = []
    for j, name in enumerate(scene["rays"]["balls"]):
        hits = []
        for d in arrays[f"rays{j:02d}.d"]:
            ok, _loc, _n, _i, ob, _m = sc.ray_cast(depsgraph, origin, Vector(d.tolist()))
            hits.append(bool(ok and ob is not None and ob.name == name))
        out.append(hits)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    scene = json.loads(a.scene.read_text())
    arrays = dict(np.load(a.scene.with_name("arrays.npz")))
    a.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    _setup(scene, a.threads)
    build(scene, arrays)
    t_build = time.perf_counter() - t0
    hits = first_hits(scene, arrays)
    img = _render(a.out / "outside.exr", scene["spp_outside"], scene["seed"])
    x, y, w, h = scene["window"]
    field = _render(a.out / "field.exr", scene["spp"], scene["seed"] + 1, (x, y, w, h))
    img[y:y + h, x:x + w] = field[y:y + h, x:x + w]
    np.save(a.out / "linear.npy", img.astype(np.float32))
    (a.out / "result.json").write_text(json.dumps({
        "blender": bpy.app.version_string, "window": [x, y, w, h], "build_s": round(t_build, 2),
        "render_s": round(time.perf_counter() - t0 - t_build, 2), "first_hit_is_ball": hits}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
