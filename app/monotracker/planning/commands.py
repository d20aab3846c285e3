"""CLI sub-command of the planning area: ``plan-layout``.

``monotracker plan-layout CT --target X,Y,Z [--entry X,Y,Z] [--balls N] [--radius MM]
[--camera cam.yaml] [--noise PX] [--json]`` loads the CT, finds its fiducials and its skin,
plans the balls and the camera (:func:`monotracker.planning.plan_layout`, room defaults of
:mod:`monotracker.planning.defaults`) and prints the suggested ball positions (LPS mm), the camera
pose ``T_ct_cam``, and the predicted error at the target (mean, 95 %, trusted share) for the
suggestion, with the worst single ball hidden, at the camera's distance limits, and for the
fiducials the CT already has. The last line is a JSON object (``--json``: only that line).
Bad input gets one line (``error: ...``), never a traceback.
"""

from __future__ import annotations

import argparse
import json
import re
import sys

from monotracker.cli_args import existing_file, finite_float, float_list, int_range
from monotracker.errors import InputError


def register(subparsers) -> None:
    from .detector_defaults import DEFAULT_FOUND_PROBABILITY, DEFAULT_NOISE_PX

    p = subparsers.add_parser(
        "plan-layout",
        help="plan where the fiducial balls and the camera go for a small error at the target",
        description="Suggest ball positions on the skin and a camera placement that minimise the predicted "
                    "error at the target with a margin for one hidden ball; print what to expect. "
                    "The last line is a JSON object.",
    )
    p.add_argument("ct", help="the planning CT: DICOM series folder or volume file")
    p.add_argument("--target", required=True, type=float_list(3), metavar="X,Y,Z", help="target, LPS mm")
    p.add_argument("--entry", type=float_list(3), default=None, metavar="X,Y,Z", help="entry on the skin, LPS mm")
    p.add_argument("--balls", type=int_range(4, 16), default=9, metavar="N", help="number of balls (4-16, default 9)")
    p.add_argument("--radius", type=finite_float(0.5, 20.0), default=None, metavar="MM",
                   help="ball radius in mm (default: the CT's fiducials' median, else 4)")
    p.add_argument("--camera", type=existing_file, default=None, metavar="CAM.yaml",
                   help="camera calibration (OpenCV YAML/XML or JSON; default: the simulated camera's)")
    p.add_argument("--noise", type=finite_float(0.005, 5.0), default=None, metavar="PX",
                   help=f"image noise of the ball centres, px (default {DEFAULT_NOISE_PX:g})")
    p.add_argument("--edge-rms", type=finite_float(0.0, 5.0), default=None, metavar="PX",
                   help="edge-fit spread of the balls that the pose tracker's shading cover will see, px "
                        "(default: the noise, as the default edge-fitted detector; 0: a detector without edge fits)")
    p.add_argument("--found", type=finite_float(0.05, 1.0), default=None, metavar="P",
                   help="each ball the camera sees is found by the detector with this probability, for the outlook "
                        f"with the detector's losses (default {DEFAULT_FOUND_PROBABILITY:g}, measured on rendered frames)")
    p.add_argument("--keep", default="", metavar="I,J,...",
                   help="indices of the CT's fiducials (as detect-ct numbers them) that stay where they are")
    p.add_argument("--quick", action="store_true", help="a coarser, quicker search (8 camera directions, no refinement)")
    p.add_argument("--json", action="store_true", help="print only the JSON line")
    # a point whose first coordinate is negative ("--target -12.5,40,88") is a value, not an option:
    # argparse only knows plain negative numbers ("-12.5") as values
    p._negative_number_matcher = re.compile(r"^-\d+(\.\d*)?([eE][-+]?\d+)?(,|$)|^-\.\d")
    p.set_defaults(func=_plan_layout)


def _keep_list(text: str, n: int) -> tuple:
    if not text.strip():
        return ()
    try:
        ids = tuple(int(t) for t in text.split(","))
    except ValueError:
        raise InputError(f"--keep {text!r} is not a list of fiducial indices (e.g. 0,3,5)") from None
    bad = [i for i in ids if not 0 <= i < n]
    if bad:
        raise InputError(f"--keep {bad[0]}: the CT has fiducials 0-{n - 1}" if n else "--keep: the CT has no fiducials")
    return ids


def _plan_layout(args: argparse.Namespace) -> int:
    import numpy as np

    from monotracker.ct import detect_fiducials, head_surface, load_volume
    from monotracker.ct.commands import _native_stderr_silenced
    from monotracker.ct.kit import FiducialKit
    from monotracker.vision.camera_model import CameraModel

    from . import DEFAULT_NOISE_PX, HeadSurface, build_problem, plan_layout

    camera = CameraModel.load(args.camera) if args.camera is not None else None
    with _native_stderr_silenced():
        vol = load_volume(args.ct)
    det = detect_fiducials(vol, kit=FiducialKit(radius_mm=args.radius))
    existing = np.array([f.centre_lps for f in det.fiducials], float).reshape(-1, 3)
    radius = args.radius or (float(np.median([f.radius_mm for f in det.fiducials])) if det.fiducials else 4.0)
    keep = _keep_list(args.keep, len(existing))
    head = HeadSurface.from_mesh(head_surface(vol))
    try:
        problem = build_problem(head, np.array(args.target), entry=None if args.entry is None else np.array(args.entry),
                                existing=existing, radius_mm=radius, camera=camera,
                                noise_px=args.noise if args.noise is not None else DEFAULT_NOISE_PX,
                                edge_rms_px=args.edge_rms, found_probability=args.found)
        progress = None if args.json else _progress_line
        plan = plan_layout(problem, args.balls, keep=keep, progress=progress,
                           n_directions=8 if args.quick else 24, refine=not args.quick)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if progress is not None:
        sys.stderr.write("\n")
    out = plan.to_dict()
    out["ct"] = str(args.ct)
    out["ct_fiducials_lps_mm"] = np.round(existing, 3).tolist()
    if not args.json:
        print(format_plan(plan, existing))
    print(json.dumps(out, separators=(",", ":")))
    return 0


def _progress_line(frac: float, msg: str) -> None:
    sys.stderr.write(f"\r{100 * frac:3.0f} % {msg:<60.60}")
    sys.stderr.flush()


def _row(label: str, p) -> list[str]:
    out = []
    e, w = p.all_seen, p.worst_hidden
    if e is None:
        return [f"  {label:<36} no pose: {p.reason}"]
    out.append(f"  {label:<36} {e.mean_mm:5.2f} {e.p95_mm:5.2f} {e.rms_mm:5.2f}  {100 * e.trusted:3.0f} %  "
               f"({e.n_balls} balls seen)")
    if w is not None:
        out.append(f"  {'  ... worst ball hidden (#%d)' % p.worst_ball:<36} {w.mean_mm:5.2f} {w.p95_mm:5.2f} "
                   f"{w.rms_mm:5.2f}  {100 * w.trusted:3.0f} %")
    elif p.margin_reason:
        out.append(f"  {'  ... one ball hidden':<36} {p.margin_reason}")
    lo = p.with_losses
    if lo is not None:
        label = "  ... with the detector's losses"
        out.append(f"  {label:<36} {'':17} {100 * lo.trusted:3.0f} %  (a pose in {100 * lo.pose:.0f} % of setups; "
                   f"{lo.phrase})")
    return out


def format_plan(plan, existing) -> str:
    """The human-readable report of a :class:`~monotracker.planning.LayoutPlan`."""
    import numpy as np

    P = plan.problem
    lines = [f"layout for target {', '.join(f'{v:.1f}' for v in P.target)} (LPS mm): {len(plan.balls)} balls of "
             f"{P.radius_mm:g} mm radius, image noise {P.noise_px:g} px, edge spread "
             f"{P.noise_px if P.edge_rms_px is None else P.edge_rms_px:g} px (the tracker's shading cover)",
             "suggested balls (centre, LPS mm):"]
    for i, (b, src) in enumerate(zip(plan.balls, plan.from_existing)):
        keep = f"   (CT fiducial {src} stays)" if src >= 0 else ""
        lines.append(f"  {i + 1:2d}: {b[0]:8.2f} {b[1]:8.2f} {b[2]:8.2f}{keep}")
    T = plan.T_ct_cam
    eye, look = T[:3, 3], T[:3, 2]
    lines.append(f"camera: at {eye[0]:.1f}, {eye[1]:.1f}, {eye[2]:.1f} LPS mm, looking along "
                 f"{look[0]:.3f}, {look[1]:.3f}, {look[2]:.3f}, {plan.camera.distance_mm:.0f} mm from the head")
    lines.append("  T_ct_cam = " + np.array2string(T, precision=4, suppress_small=True, separator=", ").replace("\n", "\n             "))
    lines.append("predicted error at the target (mm):     mean  95 %   RMS  trusted")
    lines += _row("suggestion, planned camera", plan.expected)
    lo, hi = P.space.distance_mm
    lines += _row(f"suggestion, camera at {lo:.0f} mm", plan.at_near)
    lines += _row(f"suggestion, camera at {hi:.0f} mm", plan.at_far)
    if plan.existing_here is not None:
        lines += _row("CT's fiducials, planned camera", plan.existing_here)
        lines += _row("CT's fiducials, their best camera", plan.existing_best)
    if plan.moves:
        moves = [f"#{a} -> {b + 1} ({d:.0f} mm)" for a, b, d in plan.moves if plan.from_existing[b] != a]
        if moves:
            lines.append("to go from the CT's balls to the suggestion, move: " + ", ".join(moves))
    for n in plan.notes:
        lines.append(f"note: {n}")
    return "\n".join(lines)
