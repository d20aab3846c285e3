"""``monotracker replay``: re-run detection + registration on a session recording.

    monotracker replay DIR [--json] [--tolerance-mm 0.001]

Reads a recording made with ``--record DIR`` (``serve`` or ``demo``), re-runs the estimator the
session ran on every recorded frame, and compares the poses at the planned target. The last line
printed is always one JSON object with ``frames`` (poses compared) and ``max_pose_diff_mm``
(with ``--json`` it is the only line). Exit code 0 when every pose is reproduced within the
tolerance, 1 otherwise; an incomplete or corrupt recording is refused with one line (exit 2).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from monotracker.errors import InputError


def register(subparsers) -> None:
    p = subparsers.add_parser("replay", help="re-run detection + registration on a recording and compare poses",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", type=Path, help="recording folder (written by --record)")
    p.add_argument("--json", action="store_true", help="print only the JSON result line")
    p.add_argument("--tolerance-mm", type=float, default=None,
                   help="largest accepted pose difference at the target, mm (default 0.001)")
    p.set_defaults(func=_replay)


def _replay(args) -> int:
    from monotracker.interop.replay import DEFAULT_TOLERANCE_MM, format_report, replay_recording

    tol = DEFAULT_TOLERANCE_MM if args.tolerance_mm is None else float(args.tolerance_mm)
    if not (tol > 0):
        raise InputError("--tolerance-mm must be positive")
    r = replay_recording(args.folder, tol)
    if not args.json:
        print(format_report(r))
    print(r.to_json(), flush=True)
    return 0 if r.ok else 1
