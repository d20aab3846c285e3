"""Render physically based scenes whose camera stands where the layout planner would approve it
(issue 28: reach measured where the product says the pose should be trusted).

Each scene is drawn as ``monotracker.sim.pbr.spec.make_spec`` draws it (same layouts, lamps,
skins, drapes, occluders, splits and their rules), except that camera poses are drawn from the same
distribution until the planner (``monotracker.planning.predict``: the phantom's head mesh, the
scene's balls, its default image noise and the tracker's gates) predicts the pose trusted in at
least ``planning.planner.MIN_TRUSTED`` of frames with the worst single ball hidden, the verdict
``plan_layout`` uses. The planner sees only the head: fingers, instruments and strays are placed
afterwards, as a team's would be, and may hide more than one ball. Scene indices start at
:data:`INDEX0` so that a planned scene never shares a seed with a scene of the plain sets; the
folder is ``<root>/<split>`` (default root ``$MONOTRACKER_PBR/planned``; Blender's
``<root>/blender/<split>``), scored with ``benchmarks/camera_pbr.py --root <root> [--held-out]``
(Blender: ``--root <root>/blender --renderer blender``). The held-out split is only ever scored.

Usage: PYTHONPATH=app python scripts/render_planned.py --split tuning|held_out --counts clean=10,OR=10,clutter=10
       [--root DIR] [--scene KIND:I] (one scene, for one CPU slot at a time)
       [--renderer blender --blender-python /work/bpyenv/bin/python]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

#: first scene index of the planned scenes (the plain sets use 0, 1, 2, ...)
INDEX0 = 5000


def planner_accept(phantom):
    """``accept(X, T_cam_ct)``: the planner's verdict for the balls ``X`` seen from ``T_cam_ct``."""
    from monotracker.geometry import invert_transform
    from monotracker.planning import HeadSurface, predict
    from monotracker.planning.defaults import build_problem
    from monotracker.planning.planner import MIN_TRUSTED
    from monotracker.sim.pbr.surfaces import head_mesh

    V, _N, _uv, F = head_mesh(phantom, nu=200, nv=100)
    head = HeadSurface(V, F)
    axes = np.asarray(phantom.skin_semi_axes_mm, float)

    def accept(X: np.ndarray, T_cam_ct: np.ndarray) -> bool:
        v = phantom.view_direction_lps / np.linalg.norm(phantom.view_direction_lps)
        # the scene's own target: 80 mm below the balls' centroid (make_spec)
        problem = build_problem(head, X.mean(axis=0) - 80.0 * v, existing=X, radius_mm=phantom.fiducial_radius_mm,
                                drape_offset_mm=None)
        # the balls' skin normals: the phantom's ellipsoid (exact; the planner's estimate from a
        # mesh needs the CT mesh's outward winding)
        n = (X - phantom.centre_lps) / axes**2
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        T_ct_cam = invert_transform(T_cam_ct)
        quick = predict(problem, T_ct_cam, X, n, full=False)       # RMS only: a fraction of a ms
        if quick.worst_hidden is None or not quick.worst_hidden.rms_mm <= 1.0:
            return False                                           # the gate's RMS limit alone refuses it
        p = predict(problem, T_ct_cam, X, n)
        return p.worst_hidden is not None and p.worst_hidden.trusted >= MIN_TRUSTED

    return accept


def main(argv=None) -> int:
    from monotracker.sim.pbr.build import render_scene
    from monotracker.sim.pbr.frameset import default_root
    from monotracker.sim.pbr.spec import KINDS, make_spec
    from monotracker.sim.phantom import default_phantom

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", choices=("tuning", "held_out"), required=True)
    ap.add_argument("--counts", default="clean=10,OR=10,clutter=10")
    ap.add_argument("--scene", default=None, help="KIND:I: render that one scene only (no manifest)")
    ap.add_argument("--root", type=Path, default=None)
    ap.add_argument("--renderer", choices=("mitsuba", "blender"), default="mitsuba",
                    help="blender: Cycles in a Python with bpy (--blender-python), into <root>/blender/<split>")
    ap.add_argument("--blender-python", default=None)
    a = ap.parse_args(argv)
    root = a.root or default_root() / "planned"
    folder = root / a.split if a.renderer == "mitsuba" else root / "blender" / a.split
    folder.mkdir(parents=True, exist_ok=True)
    ph = default_phantom()
    accept = planner_accept(ph)
    if a.scene:
        kind, i = a.scene.split(":")
        wanted = [(kind, int(i))]
    else:
        counts = {k: int(n) for k, n in (kv.split("=") for kv in a.counts.split(",") if kv)}
        wanted = [(k, i) for k in KINDS for i in range(counts.get(k, 0))]
    entries = []
    for kind, i in wanted:
        try:
            spec = make_spec(a.split, kind, INDEX0 + i, ph, camera_accept=accept)
        except RuntimeError:      # no camera pose the planner approves for this layout: skipped
            print(f"{a.split}/{kind}/{INDEX0 + i}: the planner approves no camera pose for this layout; skipped")
            continue
        path = render_scene(spec, folder, renderer=a.renderer, blender_python=a.blender_python)
        entries.append({"hash": path.stem, "kind": kind, "index": INDEX0 + i})
    if not a.scene:
        (folder / "manifest.json").write_text(json.dumps({"split": a.split, "renderer": a.renderer,
                                                          "scenes": entries}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
