"""``monotracker`` sub-commands of the digital twin (sim may use every lower layer, so the commands
that make simulated data live here, not in the areas whose inputs they simulate):

* ``make-sample-data [--out DIR]``: the synthetic head phantom CT and its ground truth
  (``sample_data/``, deterministic).
* ``simulate-camera --out DIR [--frames 30] [--trajectory mixed] [--events]``: simulated frames
  (PNG) and their ground truth (JSON), e.g. to try ``detect-image`` or a folder source.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from monotracker.errors import InputError


def register(subparsers) -> None:
    m = subparsers.add_parser(
        "make-sample-data",
        help="regenerate the synthetic head phantom CT and its ground truth",
        description="Write phantom_ct.nii.gz and phantom_truth.json (deterministic).",
    )
    m.add_argument("--out", default=None, metavar="DIR", help="output folder (default: the repo's sample_data/)")
    m.set_defaults(func=_make_sample_data)

    s = subparsers.add_parser("simulate-camera", help="write simulated camera frames + ground truth")
    s.add_argument("--out", required=True, help="output folder")
    s.add_argument("--frames", type=int, default=30)
    s.add_argument("--trajectory", default="mixed", help="still, drift, breathing, jumps or mixed")
    s.add_argument("--events", action="store_true", help="add occlusions, stray blobs and lighting changes")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=_simulate)


def _make_sample_data(args: argparse.Namespace) -> int:
    from monotracker.paths import sample_data_dir
    from monotracker.sim.ct_phantom import make_sample_ct

    out = Path(args.out) if args.out else sample_data_dir()
    ct_path, truth_path = make_sample_ct(out)
    print(f"wrote {ct_path} ({ct_path.stat().st_size / 1e6:.1f} MB) and {truth_path}")
    return 0


def _simulate(args) -> int:
    import cv2

    from monotracker.sim.camera_sim import SimulatedCamera, random_events
    from monotracker.sim.trajectories import make_trajectory

    if args.frames < 1:
        raise InputError("--frames must be at least 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cam = SimulatedCamera(trajectory=make_trajectory(args.trajectory, seed=args.seed), seed=args.seed,
                          max_frames=args.frames)
    if args.events:
        cam.events = random_events(args.frames / cam.fps, cam.rest_projection(), seed=args.seed)
    cam.camera.save(out / "camera.yml")
    truth = []
    for f in cam:
        cv2.imwrite(str(out / f"frame_{f.index:05d}.png"), f.image)
        tr = f.truth
        truth.append({"index": f.index, "t_s": tr.t_s, "T_cam_ct": tr.T_cam_ct.round(6).tolist(),
                      "ellipse_centres_px": tr.ellipse_centres_px.round(4).tolist(),
                      "visible": tr.visible.tolist()})
    (out / "truth.json").write_text(json.dumps(truth))
    print(f"wrote {args.frames} frames, camera.yml and truth.json to {out}")
    return 0
