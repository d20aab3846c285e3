"""CLI sub-command of the CT area: ``detect-ct`` (``make-sample-data`` is the digital twin's: ``sim/commands.py``)."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys

from monotracker.errors import InputError


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "detect-ct",
        help="find the sphere fiducials in a CT (DICOM folder, .nii[.gz], .nrrd, .mha)",
        description="Load a CT and print its sphere fiducials (centre LPS mm, radius, score).",
    )
    p.add_argument("path", help="DICOM series folder or volume file")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--radius", type=float, default=None, metavar="MM", help="nominal ball radius in mm (default: estimate it)")
    p.add_argument("--density", type=float, default=None, metavar="HU", help="the balls' density in HU when known (e.g. 1500 ceramic); metal of another density is rejected")
    p.add_argument("--series", default=None, metavar="UID", help="DICOM Series Instance UID to use when the folder holds several")
    p.add_argument("--list-series", action="store_true", help="list the DICOM series of the folder (uid, description, slices, spacing, tilt) and stop")
    p.add_argument("--baseline", action="store_true", help="use the paper's recipe (threshold + DBSCAN + centroid) instead")
    p.set_defaults(func=_detect_ct)


def _detect_ct(args: argparse.Namespace) -> int:
    try:
        return _detect_ct_run(args)
    except KeyboardInterrupt:
        print("interrupted (Ctrl-C): CT detection stopped, nothing written", file=sys.stderr)
        return 130


def _detect_ct_run(args: argparse.Namespace) -> int:
    from monotracker.ct.fiducials import detect_fiducials, detect_fiducials_paper
    from monotracker.ct.volume import load_volume

    from monotracker.ct.kit import FiducialKit

    try:  # the kit's own checks (the same as the app's), before the slow load
        kit = FiducialKit(radius_mm=args.radius, density_hu=args.density)
    except ValueError as exc:
        raise InputError(str(exc).replace("fiducial radius", "--radius").replace("fiducial density", "--density")) from None
    if args.list_series:
        return _list_series(args)
    with _native_stderr_silenced():
        vol = load_volume(args.path, series=args.series)
    if args.baseline:
        det = detect_fiducials_paper(vol)
    else:
        det = detect_fiducials(vol, kit=kit)
    if args.json:
        out = det.to_dict()
        out["volume"] = {
            "path": str(args.path),
            "size_ijk": list(vol.size_ijk),
            "spacing_mm": [float(s) for s in vol.spacing_mm],
            "notes": vol.notes,
        }
        json.dump(out, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(format_detection(det, vol))
    return 0 if det.ok else 1


def _list_series(args: argparse.Namespace) -> int:
    from monotracker.ct.dicom_series import list_series

    infos = list_series(args.path)
    if args.json:
        json.dump({"series": [i.to_dict() for i in infos]}, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0 if infos else 1
    if not infos:
        print(f"no DICOM series in {args.path}")
        return 1
    for i in infos:
        sp = " x ".join(f"{s:.3g}" for s in i.spacing_mm)
        print(f"{i.uid}  {i.description or '-'!s}  {i.slices} slices  spacing {sp} mm  tilt {i.tilt_deg:.1f} deg"
              + ("" if i.ok else "  REFUSED"))
        for n in i.notes:
            print(f"    {n}")
    return 0


@contextlib.contextmanager
def _native_stderr_silenced():
    """ITK's MetaIO prints its own lines on a damaged file straight to the C stderr; the
    operator should see only our one-line error. CLI only (single-threaded), never the app."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except OSError:
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def format_detection(det, vol) -> str:
    """Human-readable table of a :class:`FiducialDetection` for ``vol``."""
    lines = [f"CT {vol.source}: {vol.describe()}"]
    lines += [f"note: {n}" for n in vol.notes]
    if det.ok:
        lines.append(f"{len(det.fiducials)} fiducials ({det.method} method, threshold {det.threshold_hu:.0f} HU, {det.elapsed_s * 1000:.0f} ms), LPS mm:")
        lines.append(f"{'#':>3} {'L':>9} {'P':>9} {'S':>9} {'radius':>7} {'score':>6}")
        for i, f in enumerate(det.fiducials):
            c = f.centre_lps
            lines.append(f"{i:>3} {c[0]:9.3f} {c[1]:9.3f} {c[2]:9.3f} {f.radius_mm:7.2f} {f.score:6.2f}")
    else:
        lines.append(f"no fiducials: {det.reason}")
    for r in det.rejected:
        c = r.centre_lps
        lines.append(f"rejected blob at ({c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}): {r.reason}")
    lines += [f"note: {n}" for n in det.notes]
    return "\n".join(lines)
