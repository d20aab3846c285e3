"""Render a :class:`~.spec.SceneSpec` with Blender's Cycles: a second physically based renderer
nobody on this project wrote, with real sub-surface scattering in the skin (issue 28).

Blender is GPL and large, so it never enters the project's environment: Cycles runs in a Python
of its own that has the ``bpy`` wheel (``python3.11 -m venv /work/bpyenv && /work/bpyenv/bin/pip
install bpy==4.5.4 numpy``), named by ``--blender-python`` or ``$MONOTRACKER_BLENDER_PYTHON``.
This module (project side, numpy only) writes the scene as a *package* (:func:`export_package`:
meshes, curves, textures and parameters, all in CT millimetres, colours linear Rec.709), runs
:mod:`.blender_scene` (the only code that imports ``bpy``) on it in that Python, and reads back
the linear render and the per-ball ray cast.

Differences from the Mitsuba frames, chosen before any scoring:

* **lens**: a pinhole (Blender's perspective camera with the calibrated K as focal length and
  lens shift); the spec's distortion is set to zero (:func:`blender_spec`), so truth and camera
  model match the frames exactly; pixel area integrated by a 1-px box filter as in Mitsuba;
* **skin**: Principled BSDF with random-walk sub-surface scattering (weight 1, mean free path
  R, G, B 3.67, 1.37, 0.68 mm x 0.5: Jensen et al. 2001's skin, halved for a shaved scalp over
  bone), the same albedo texture, roughness and specular level;
* **balls**: Principled (matte: roughness sqrt(0.35), the Mitsuba GGX alpha; glossy: a clear
  coat of roughness 0.03 over a roughness-0.5 base); gloves Principled roughness sqrt(0.3);
  steel metallic (chromium's colour) with the spec's roughness; drapes and towel diffuse with the
  same textures and fold normals; hair tubes of the spec's radius;
* **lights**: the lamps as emitting discs of the same radiance, the ambient as the world colour;
  6 bounces of each kind, no clamping, no denoising;
* textures may be mirrored relative to Mitsuba's (uv conventions differ): same statistics.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from monotracker.errors import InputError

from .spec import GLOVE_RGB, HAIR_RGB, SceneSpec, _perp_frame, _unit, field_window
from .surfaces import (HAIR_RADIUS_MM, drape_sheet, drape_texture, hair_curves, head_mesh, plain_texture,
                       skin_texture, towel_band)
from .truth import visibility_rays

#: the version tag in a Blender frame's spec (part of its scene hash)
RENDERER_VERSION = "blender-cycles-1"
#: mean free path of the skin's sub-surface scattering, R G B mm (Jensen et al. 2001 x 0.5)
SKIN_SSS_RADIUS_MM = (3.67, 1.37, 0.68)
SKIN_SSS_SCALE = 0.5
#: chromium's linear RGB reflectance at normal incidence (steel instrument)
STEEL_RGB = (0.55, 0.556, 0.554)
SCENE_SCRIPT = Path(__file__).with_name("blender_scene.py")
#: where the work machines keep the Python with bpy when nothing else names one
DEFAULT_BLENDER_PYTHON = "/work/bpyenv/bin/python"


def blender_spec(spec: SceneSpec) -> SceneSpec:
    """The spec a Blender frame records: a pinhole lens (distortion zero) and the Blender
    renderer's tag (so its hash never collides with the Mitsuba frame of the same scene)."""
    return replace(spec, dist=tuple(0.0 for _ in spec.dist), renderer=RENDERER_VERSION)


def blender_python(explicit: str | None = None) -> str:
    """The Python that has ``bpy``: ``explicit``, else ``$MONOTRACKER_BLENDER_PYTHON``, else
    :data:`DEFAULT_BLENDER_PYTHON`; one-line InputError when none is there."""
    for cand in (explicit, os.environ.get("MONOTRACKER_BLENDER_PYTHON"), DEFAULT_BLENDER_PYTHON):
        if cand and Path(cand).exists():
            return str(cand)
    raise InputError("the Blender renderer needs a Python with the bpy wheel (python3.11 -m venv /work/bpyenv && "
                     "/work/bpyenv/bin/pip install bpy==4.5.4 numpy); name it with --blender-python or "
                     "MONOTRACKER_BLENDER_PYTHON")


def _disc_mesh(centre, normal, radius, n: int = 96) -> tuple[np.ndarray, np.ndarray]:
    e1, e2 = _perp_frame(_unit(normal))
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rim = np.asarray(centre, float) + radius * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2)
    V = np.vstack([np.asarray(centre, float)[None], rim])
    F = np.stack([np.zeros(n, int), 1 + np.arange(n), 1 + (np.arange(n) + 1) % n], -1)
    # wind so that the face normal is ``normal``
    if np.cross(V[F[0, 1]] - V[0], V[F[0, 2]] - V[0]) @ np.asarray(normal, float) < 0:
        F = F[:, [0, 2, 1]]
    return V, F.astype(np.int32)


def export_package(spec: SceneSpec, folder: Path, n_rays: int = 2048, rays: list | None = None) -> Path:
    """Write ``spec`` as a Blender scene package into ``folder``: ``scene.json`` (camera,
    window, samples, materials, objects) and ``arrays.npz`` (meshes, textures, hair, the
    visibility rays: ``rays``, else :func:`~.truth.visibility_rays` of ``n_rays`` per ball).
    ``spec`` should be a :func:`blender_spec` (pinhole). Returns the JSON path."""
    from monotracker.sim.phantom import default_phantom

    if any(abs(float(d)) > 0 for d in spec.dist):
        raise ValueError("Blender renders a pinhole: pass blender_spec(spec)")
    folder.mkdir(parents=True, exist_ok=True)
    ph = default_phantom()
    arrays: dict[str, np.ndarray] = {}
    objects: list[dict] = []

    def mesh(name, V, F, material, uv=None):
        arrays[f"{name}.V"] = np.asarray(V, np.float64)
        arrays[f"{name}.F"] = np.asarray(F, np.int32)
        if uv is not None:
            arrays[f"{name}.uv"] = np.asarray(uv, np.float32)
        objects.append({"type": "mesh", "name": name, "material": material})

    def sphere(name, c, r, material):
        objects.append({"type": "sphere", "name": name, "centre": [float(v) for v in c], "radius": float(r),
                        "material": material})

    def capsule(name, a, b, r, material):
        objects.append({"type": "capsule", "name": name, "a": [float(v) for v in a], "b": [float(v) for v in b],
                        "radius": float(r), "material": material})

    materials = {
        "skin": {"kind": "skin", "texture": "tex.skin", "roughness": spec.skin.roughness,
                 "specular": spec.skin.specular, "sss_radius": list(SKIN_SSS_RADIUS_MM), "sss_scale": SKIN_SSS_SCALE},
        "sheet": {"kind": "diffuse", "texture": "tex.sheet", "normal_map": "tex.sheet_normals"},
        "towel": {"kind": "diffuse", "texture": "tex.towel"},
        "ball": {"kind": "ball", "rgb": list(spec.ball_rgb), "finish": spec.ball_finish},
        "green": {"kind": "plastic", "rgb": list(spec.ball_rgb), "roughness": float(np.sqrt(0.3))},
        "steel": {"kind": "metal", "rgb": list(STEEL_RGB), "roughness": 0.0},
        "hair": {"kind": "diffuse", "rgb": list(HAIR_RGB[spec.hair_colour])},
    }
    arrays["tex.skin"] = skin_texture(spec)
    arrays["tex.sheet"] = drape_texture(spec.drapes, spec.drape_seed)
    M, normals = drape_sheet(ph, spec.drape_seed)
    arrays["tex.sheet_normals"] = normals
    arrays["tex.towel"] = plain_texture(spec.towel, spec.drape_seed)

    V, _, uv, F = head_mesh(ph)
    mesh("head", V, F, "skin", uv)
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    Vs = (M @ np.c_[corners, np.zeros(4), np.ones(4)].T).T[:, :3]
    mesh("sheet", Vs, np.array([[0, 1, 2], [0, 2, 3]]), "sheet", (corners + 1.0) / 2.0)
    V, _, uv, F = towel_band(ph, spec.drape_seed)
    mesh("towel", V, F, "towel", uv)
    for j, c in enumerate(spec.fiducials):
        sphere(f"ball{j:02d}", c, spec.radius_mm, "ball")
    lamps = []
    for k, lamp in enumerate(spec.lamps):
        area = np.pi * lamp.radius_mm**2
        d2 = float(np.sum((np.array(lamp.centre) - spec.fiducials.mean(0)) ** 2))
        radiance = np.array(lamp.rgb) * lamp.irradiance * d2 / area
        Vd, Fd = _disc_mesh(lamp.centre, lamp.normal, lamp.radius_mm)
        arrays[f"lamp{k}.V"], arrays[f"lamp{k}.F"] = Vd, Fd
        lamps.append({"name": f"lamp{k}", "radiance": [float(v) for v in radiance]})
    for k, f in enumerate(spec.fingers):
        name = f"glove{k}"
        materials[name] = {"kind": "plastic", "rgb": list(GLOVE_RGB[f.glove]), "roughness": float(np.sqrt(0.3))}
        tip = np.array(f.tip)
        capsule(f"finger{k}", tip, tip + f.length_mm * np.array(f.direction), f.radius_mm, name)
    for k, r in enumerate(spec.rods):
        name = f"steel{k}"
        materials[name] = {"kind": "metal", "rgb": list(STEEL_RGB), "roughness": float(np.sqrt(r.roughness))}
        capsule(f"rod{k}", r.start, r.end, r.radius_mm, name)
    for k, s in enumerate(spec.strays):
        c, ax = np.array(s.centre), np.array(s.axis)
        if s.shape == "sticker":
            Vd, Fd = _disc_mesh(c, ax, s.size_mm)
            mesh(f"stray{k}", Vd, Fd, "green")
        elif s.shape == "cap":
            capsule(f"stray{k}", c - 0.5 * s.length_mm * ax, c + 0.5 * s.length_mm * ax, s.size_mm, "green")
        elif s.shape == "ball":
            sphere(f"stray{k}", c, s.size_mm, "green")
        else:
            materials["led"] = {"kind": "emission", "rgb": [0.3, 6.0, 0.5]}
            sphere(f"stray{k}", c, s.size_mm, "led")
    strands = hair_curves(spec, ph)
    if strands:
        arrays["hair.points"] = np.concatenate(strands).astype(np.float64)
        arrays["hair.counts"] = np.array([len(s) for s in strands], np.int32)
    rays = visibility_rays(spec, n_rays) if rays is None else rays
    for j, r in enumerate(rays):
        arrays[f"rays{j:02d}.d"] = r.directions_ct
    x, y, w, h = field_window(spec)
    scene = {
        "renderer": RENDERER_VERSION,
        "camera": {"K": [list(row) for row in spec.K], "image_size": list(spec.image_size),
                   "T_ct_cam": np.linalg.inv(spec.T).tolist()},
        "window": [int(x), int(y), int(w), int(h)], "spp": int(spec.spp), "spp_outside": int(spec.spp_outside),
        "seed": int(spec.seed), "max_bounces": 6, "ambient_rgb": list(spec.ambient_rgb),
        "materials": materials, "objects": objects, "lamps": lamps,
        "hair": {"radius": HAIR_RADIUS_MM, "material": "hair"} if strands else None,
        "rays": {"origin": [float(v) for v in spec.eye_ct], "balls": [f"ball{j:02d}" for j in range(len(rays))]},
    }
    np.savez(folder / "arrays.npz", **arrays)
    path = folder / "scene.json"
    path.write_text(json.dumps(scene, indent=1))
    return path


def render_linear(spec: SceneSpec, python: str | None = None, threads: int | None = None,
                  log=print) -> tuple[np.ndarray, None, dict]:
    """Render ``spec`` (made a :func:`blender_spec` here) with Cycles: (linear RGB float32 (h, w,
    3), None (no coverage image), info: seconds, samples, Blender version, visible fraction per
    ball (the first hit of each :func:`~.truth.visibility_rays` ray is the ball))."""
    py = blender_python(python)
    spec = blender_spec(spec) if spec.renderer != RENDERER_VERSION else spec
    threads = int(threads or os.environ.get("MONOTRACKER_RENDER_THREADS", "1"))
    with tempfile.TemporaryDirectory(prefix="mt_blender_") as tmp:
        t0 = time.perf_counter()
        rays = visibility_rays(spec)
        pkg = export_package(spec, Path(tmp), rays=rays)
        t_export = time.perf_counter() - t0
        proc = subprocess.run([py, str(SCENE_SCRIPT), str(pkg), str(Path(tmp) / "out"), "--threads", str(threads)],
                              capture_output=True, text=True)
        if proc.returncode != 0:
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-5:]
            raise InputError("Blender render failed: " + " | ".join(tail))
        lin = np.load(Path(tmp) / "out" / "linear.npy")
        res = json.loads((Path(tmp) / "out" / "result.json").read_text())
    vis = [float(np.mean(np.asarray(hit, bool) & r.counts)) for hit, r in zip(res["first_hit_is_ball"], rays)]
    info = {"renderer": RENDERER_VERSION, "blender": res["blender"], "spp": int(spec.spp),
            "spp_outside": int(spec.spp_outside), "field_window": res["window"], "threads": threads,
            "export_s": round(t_export, 2), "render_s": res["render_s"], "visible_fraction": [round(v, 4) for v in vis]}
    return lin.astype(np.float32), None, info


if __name__ == "__main__":  # pragma: no cover - a manual smoke run
    from .spec import make_spec

    s = make_spec("tuning", "clean", 0)
    img, _, inf = render_linear(s)
    print(img.shape, inf, file=sys.stderr)
