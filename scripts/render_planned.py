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
``<root>/blender/<split>``, ``sim.pbr.build.default_folder``), scored with
``benchmarks/camera_pbr.py --root <root> [--held-out] [--renderer blender]``. The held-out split is only ever scored.

Usage: PYTHONPATH=app python scripts/render_planned.py --split tuning|held_out --counts clean=10,OR=10,clutter=10
       [--root DIR] [--scene KIND:I] (one scene, for one CPU slot at a time)
       [--plan-balls N] (the planner's layout AND camera for N balls in every scene, <root>/plan<N>)
       [--renderer blender --blender-python /work/bpyenv/bin/python]
       [--optics hd|wide] (the same scenes through another camera, ``sim.pbr.spec.OPTICS``, into <root>/<optics>;
       with --plan-balls the layout and camera are planned for that camera, as the product's planner is given it)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

#: first scene index of the planned scenes (the plain sets use 0, 1, 2, ...)
INDEX0 = 5000
#: ``--plan-balls``: balls are kept this far (deg, about the head's centre) inside the scenes'
#: towel, which starts 60 deg off the view direction and rises up to ~14 mm off the skin
TOWEL_POLAR_DEG = 50.0


def planner_accept(phantom, camera=None):
    """``accept(X, T_cam_ct)``: the planner's verdict for the balls ``X`` seen from ``T_cam_ct``
    through ``camera`` (None: the generator's default camera)."""
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
                                drape_offset_mm=None, camera=camera)
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


def planned_layout(phantom, n_balls: int, camera=None) -> tuple:
    """The layout planner's full plan for ``n_balls`` balls on ``phantom``'s head (cameras about
    the phantom's view direction, a drape plane that keeps the balls off the scenes' towel, the
    target 80 mm below the phantom's own balls' centroid), for ``camera`` (a CameraModel; None:
    the generator's default camera, as the product's planner is given the session's): (ball
    centres (n, 3) CT mm, T_cam_ct, the plan). What ``--plan-balls`` renders: a layout and a
    camera the planner chose."""
    from monotracker.geometry import invert_transform
    from monotracker.planning import HeadSurface, plan_layout
    from monotracker.planning.defaults import build_problem
    from monotracker.sim.pbr.surfaces import head_mesh

    V, _N, _uv, F = head_mesh(phantom, nu=200, nv=100)
    v = phantom.view_direction_lps / np.linalg.norm(phantom.view_direction_lps)
    target = phantom.fiducial_centres_lps.mean(axis=0) - 80.0 * v
    head = HeadSurface(V, F[:, ::-1])        # head_mesh winds its faces inwards; the planner needs them out
    # the scenes' towel covers the skin from TOWEL_POLAR_DEG off the view direction (about the
    # phantom's centre, surfaces.towel_band): the planner's drape plane where the skin is that far
    # off it, at its highest, so that no ball goes under the towel
    e1 = np.cross(v, [1.0, 0.0, 0.0] if abs(v[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(v, e1)
    phi = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    th = np.radians(TOWEL_POLAR_DEG)
    d = np.cos(th) * v + np.sin(th) * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    a = np.asarray(phantom.skin_semi_axes_mm, float)
    rim = phantom.centre_lps + d / np.sqrt(np.sum(d**2 / a**2, axis=1))[:, None]
    offset = float(np.max((rim - head.centre) @ v))
    problem = build_problem(head, target, radius_mm=phantom.fiducial_radius_mm, drape_offset_mm=offset,
                            axis=v, camera=camera)     # cameras around the scenes' own view direction
    plan = plan_layout(problem, n_balls=int(n_balls))
    return plan.balls, invert_transform(plan.T_ct_cam), plan


def main(argv=None) -> int:
    from monotracker.sim.pbr.build import RENDERERS, default_folder, render_scene
    from monotracker.sim.pbr.frameset import default_root
    from monotracker.sim.pbr.spec import KINDS, OPTICS, make_spec, optics_camera, with_optics
    from monotracker.sim.phantom import default_phantom

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", choices=("tuning", "held_out"), required=True)
    ap.add_argument("--counts", default="clean=10,OR=10,clutter=10")
    ap.add_argument("--scene", action="append", default=None,
                    help="KIND:I: render that scene only (repeatable; no manifest): the plan is made once for all")
    ap.add_argument("--root", type=Path, default=None)
    ap.add_argument("--renderer", choices=RENDERERS, default="mitsuba",
                    help="blender: Cycles in a Python with bpy (--blender-python), into <root>/blender/<split>")
    ap.add_argument("--blender-python", default=None)
    ap.add_argument("--plan-balls", type=int, default=None,
                    help="N: every scene uses the layout planner's full plan for N balls (its layout AND its "
                         "camera), into <root>/plan<N>/<split>; lamps, skin, occluders drawn per scene")
    ap.add_argument("--optics", choices=tuple(OPTICS), default="native",
                    help="hd: 1920x1080, every px length x1.5; wide: f = 800 px on the same sensor (sim.pbr.spec.OPTICS): "
                         "the same scenes and camera poses through optics the generator never uses, into <root>/<optics>")
    a = ap.parse_args(argv)
    scenes = [sc.split(":") for sc in a.scene or []]
    bad = [sc for sc, parts in zip(a.scene or [], scenes)
           if len(parts) != 2 or parts[0] not in KINDS or not parts[1].isdigit()]
    if bad:       # said before the plan is made (a minute), not after
        print(f"error: --scene takes KIND:I with KIND one of {', '.join(KINDS)} (e.g. OR:3), not {' '.join(bad)}",
              file=sys.stderr)
        return 2
    root = a.root or default_root() / "planned"
    if a.optics != "native":
        root = root / a.optics
    if a.plan_balls is not None:
        root = root / f"plan{a.plan_balls}"
    folder = default_folder(a.split, a.renderer, root)
    folder.mkdir(parents=True, exist_ok=True)
    ph = default_phantom()
    accept, fixed = None, {}
    if a.plan_balls is None:
        accept = planner_accept(ph, optics_camera(a.optics))
    else:
        X, T, plan = planned_layout(ph, a.plan_balls, optics_camera(a.optics))   # planned for the lens used
        fixed = {"layout": X, "T_cam_ct": T}
        wl = plan.expected.with_losses
        print(f"plan for {a.plan_balls} balls: camera {plan.expected.distance_mm:.0f} mm, "
              f"worst hidden trusted {plan.expected.worst_hidden.trusted if plan.expected.worst_hidden else 0:.2f}, "
              f"with losses {wl.trusted if wl else float('nan'):.2f}, balls for losses {plan.balls_for_losses}")
    if a.scene:
        wanted = [(kind, int(i)) for kind, i in scenes]
    else:
        counts = {k: int(n) for k, n in (kv.split("=") for kv in a.counts.split(",") if kv)}
        wanted = [(k, i) for k in KINDS for i in range(counts.get(k, 0))]
    entries = []
    for kind, i in wanted:
        try:
            spec = make_spec(a.split, kind, INDEX0 + i, ph, camera_accept=accept, **fixed)
        except RuntimeError:      # no camera pose the planner approves for this layout: skipped
            print(f"{a.split}/{kind}/{INDEX0 + i}: the planner approves no camera pose for this layout; skipped")
            continue
        path = render_scene(with_optics(spec, a.optics), folder, renderer=a.renderer, blender_python=a.blender_python)
        entries.append({"hash": path.stem, "kind": kind, "index": INDEX0 + i})
    if not a.scene:
        (folder / "manifest.json").write_text(json.dumps({"split": a.split, "renderer": a.renderer,
                                                          "scenes": entries}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
