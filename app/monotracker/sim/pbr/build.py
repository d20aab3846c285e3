"""Render frame sets (cached by scene hash) and cut the small committed set.

    python -m monotracker.sim.pbr render --split tuning [--counts clean=20,OR=20,clutter=20] [--root DIR]
                                         [--renderer mitsuba|blender [--blender-python PATH]]
    python -m monotracker.sim.pbr crops --split tuning --out tests/data/pbr/tuning [--per-kind 6]

``render`` skips every scene whose ``<hash>.json`` exists (the hash covers the whole spec and the
renderer version, so a changed scene is rendered anew); it writes ``manifest.json`` listing the
set's scenes. ``crops`` cuts each scene to its surgical field (``spec.field_window``: the balls and 90 px round
them, even offsets so the Bayer phase stays that of the full sensor) for the committed test set; the held-out split is refused
there (it is only ever scored, never committed).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from monotracker.errors import InputError

from .frameset import default_root, list_scenes, load_scene, save_scene
from .spec import KINDS, SPLITS, SceneSpec, SetPlan, field_window, make_spec, scene_hash
from .truth import scene_truth


#: the renderers a frame set can come from (:func:`_backend` maps each to its ``render_linear``
#: and to the spec its frames record: Blender renders a pinhole, :func:`.blender_render.blender_spec`)
RENDERERS = ("mitsuba", "blender")


def renderer_name(version: str) -> str:
    """The :data:`RENDERERS` name of a frame's recorded ``SceneSpec.renderer`` version
    (``pbr-N``: Mitsuba, ``blender-cycles-N``: Blender)."""
    return "blender" if str(version).startswith("blender-") else "mitsuba"


def _backend(renderer: str, spec: SceneSpec, blender_python: str | None):
    """(the spec the frame records, a function rendering it: () -> (linear, coverage, info))."""
    if renderer == "mitsuba":
        from .mitsuba_render import render_linear

        return spec, lambda: render_linear(spec)
    if renderer == "blender":
        from . import blender_render

        bspec = blender_render.blender_spec(spec)
        return bspec, lambda: blender_render.render_linear(bspec, blender_python)
    raise InputError(f"renderer must be one of {RENDERERS}, got {renderer!r}")


def default_folder(split: str, renderer: str = "mitsuba", root: Path | None = None) -> Path:
    """Where a split's frames live: ``<root>/<split>`` (Mitsuba) or ``<root>/blender/<split>``
    (Blender), ``root`` by default ``$MONOTRACKER_PBR``: the one rule for every tool that renders
    or scores a set (until 2026-12-01 a given ``root`` held Blender's frames directly while
    ``scripts/render_planned.py`` put them under ``<root>/blender``, and the benchmark scored
    Mitsuba's frames as Blender's)."""
    base = root or default_root()
    return base / split if renderer == "mitsuba" else base / renderer / split


def render_scene(spec: SceneSpec, folder: Path, log=print, renderer: str = "mitsuba",
                 blender_python: str | None = None) -> Path:
    """Render ``spec`` with ``renderer`` (:data:`RENDERERS`) into ``folder`` unless cached;
    returns the JSON path."""
    from .mitsuba_render import auto_exposure, encode_srgb

    spec, render = _backend(renderer, spec, blender_python)
    out = folder / f"{scene_hash(spec)}.json"
    if out.exists():
        return out
    t0 = time.perf_counter()
    lin, cov, info = render()
    truth = scene_truth(spec, info["visible_fraction"])
    c = truth.ellipse_centres_px
    gain = auto_exposure(lin, (*c.min(axis=0), *c.max(axis=0)))
    save_scene(folder, spec, encode_srgb(lin * gain), truth, info, gain, coverage=cov)
    log(f"{spec.split}/{spec.kind}/{spec.index:03d} {out.stem}: rendered in {time.perf_counter() - t0:.1f} s "
        f"({renderer} {info['render_s']} s), visible {np.round(info['visible_fraction'], 2).tolist()}")
    return out


def render_set(split: str, counts: dict, root: Path | None = None, log=print, renderer: str = "mitsuba",
               blender_python: str | None = None) -> Path:
    """Render (or reuse) every scene of ``split``; write the manifest; returns the set folder."""
    folder = default_folder(split, renderer, root)
    folder.mkdir(parents=True, exist_ok=True)
    specs = SetPlan(split, counts).specs()
    entries = []
    for spec in specs:
        path = render_scene(spec, folder, log, renderer, blender_python)
        entries.append({"hash": path.stem, "kind": spec.kind, "index": spec.index})
        (folder / "manifest.json").write_text(json.dumps({"split": split, "renderer": renderer,
                                                          "scenes": entries}, indent=1))
    if split == "held_out":
        (folder / "README").write_text("Held-out frames: only ever scored (benchmarks/camera_pbr.py --held-out).\n"
                                       "Do not look at them, tune on them, or commit them.\n")
    return folder


def commit_box(spec: SceneSpec) -> tuple[int, int, int, int]:
    """The committed crop of a scene: its surgical field (``field_window``) grown to hold the
    principal point with 16 px to spare (a crop's camera model must keep it inside), even."""
    x, y, w, h = field_window(spec)
    cx, cy = spec.K[0][2], spec.K[1][2]
    W, H = spec.image_size
    x0, y0 = min(x, int(cx - 16) // 2 * 2), min(y, int(cy - 16) // 2 * 2)
    x1, y1 = min(W, max(x + w, int(cx + 17) // 2 * 2 + 2)), min(H, max(y + h, int(cy + 17) // 2 * 2 + 2))
    return max(0, x0), max(0, y0), x1 - max(0, x0), y1 - max(0, y0)


def write_crops(split: str, out: Path, per_kind: int, root: Path | None = None, log=print) -> list[Path]:
    """Cut the first ``per_kind`` scenes of each kind of ``split`` to their balls and store them in
    ``out`` (the committed test set). Held-out scenes are refused."""
    if split == "held_out":
        raise InputError("the held-out set is only ever scored: it is never committed")
    folder = (root or default_root()) / split
    written = []
    for kind in KINDS:
        for s in list_scenes(folder, (kind,))[:per_kind]:
            x, y, w, h = commit_box(s.spec)
            meta = json.loads(s.path.read_text())
            truth = scene_truth(s.spec, meta["truth"]["visible_fraction"])
            cov = None if s.coverage is None else s.coverage[y:y + h, x:x + w]
            p = save_scene(out, s.spec, s.image[y:y + h, x:x + w], truth, meta["render"], s.exposure, (x, y, w, h),
                           coverage=cov)
            log(f"{p.name}: {kind} {w}x{h} {p.stat().st_size / 1024:.0f} kB")
            written.append(p)
    return written


def _counts(text: str) -> dict:
    out = {}
    for part in text.split(","):
        k, _, v = part.partition("=")
        if k not in KINDS or not v.isdigit():
            raise InputError(f"--counts: expected kind=N with kind in {KINDS}, got {part!r}")
        out[k] = int(v)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m monotracker.sim.pbr", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("render", help="render a split's scenes (cached by scene hash)")
    r.add_argument("--split", choices=SPLITS, required=True)
    r.add_argument("--counts", default="clean=20,OR=20,clutter=20")
    r.add_argument("--root", type=Path, default=None)
    r.add_argument("--scene", action="append", default=[], metavar="KIND:INDEX",
                   help="render only this scene (repeatable): lets a wrapper take one CPU slot per scene")
    r.add_argument("--renderer", choices=RENDERERS, default="mitsuba",
                   help="mitsuba (default; <root>/<split>) or blender (Cycles, pinhole; <root>/blender/<split>); "
                        "<root> is $MONOTRACKER_PBR unless --root")
    r.add_argument("--blender-python", default=None, help="the Python with the bpy wheel (blender only)")
    c = sub.add_parser("crops", help="cut the committed tuning crops")
    c.add_argument("--split", choices=SPLITS, default="tuning")
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--per-kind", type=int, default=6)
    c.add_argument("--root", type=Path, default=None)
    a = ap.parse_args(argv)
    try:
        if a.cmd == "render" and a.scene:
            folder = default_folder(a.split, a.renderer, a.root)
            for item in a.scene:
                kind, _, idx = item.partition(":")
                if kind not in KINDS or not idx.isdigit():
                    raise InputError(f"--scene: expected KIND:INDEX with KIND in {KINDS}, got {item!r}")
                render_scene(make_spec(a.split, kind, int(idx)), folder, renderer=a.renderer,
                             blender_python=a.blender_python)
        elif a.cmd == "render":
            print(render_set(a.split, _counts(a.counts), a.root, renderer=a.renderer,
                             blender_python=a.blender_python))
        else:
            write_crops(a.split, a.out, a.per_kind, a.root)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


__all__ = ["render_scene", "render_set", "write_crops", "load_scene", "main"]
