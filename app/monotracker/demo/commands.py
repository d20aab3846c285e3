"""``monotracker demo --headless``: the closed loop on the digital twin, summarised.

    monotracker demo --headless --seconds S [--trajectory still|drift|breathing|jumps]
        [--fault none|camera-freeze|occlude-all|robot-disconnect|bad-pose|camera-bump|camera-sag] [--fault-at T]
        [--seed N] [--home DIR] [--json] [--record DIR] [--igtl-port PORT [--allow-remote]]

Runs on a simulated clock (see ``monotracker.demo.run``); ``--seconds`` is tracking time.
Exit code 0 when the run completed and, for a fault, the arm came to a standstill and the plan
is intact; 1 otherwise (the summary says why).
"""

from __future__ import annotations

import argparse
import sys

from monotracker.cli_args import finite_float, home_folder, int_range
from monotracker.engine.config import FAULTS, TRAJECTORIES
from monotracker.errors import InputError

MAX_DEMO_SECONDS = 3600.0


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the closed loop on the digital twin (camera + arm simulated)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--headless", action="store_true", help="no web app: run and print a summary")
    p.add_argument("--seconds", type=finite_float(0.0, MAX_DEMO_SECONDS, lo_open=True), default=10.0,
                   help=f"tracking time in simulated seconds, > 0 and <= {MAX_DEMO_SECONDS:g} (default 10)")
    p.add_argument("--trajectory", choices=TRAJECTORIES, default="breathing", help="head motion (default breathing)")
    p.add_argument("--fault", choices=FAULTS, default="none", help="fault to inject while tracking")
    p.add_argument("--fault-at", type=finite_float(0.0, MAX_DEMO_SECONDS), default=None, metavar="T",
                   help="seconds after tracking starts to inject the fault (default: half-way, >= 3 s)")
    p.add_argument("--seed", type=int_range(0, 2**32 - 1), default=0, help="simulator noise seed, 0 .. 2^32-1")
    p.add_argument("--home", type=home_folder, default=None, help="session folder (default: a temporary one)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.add_argument("--record", type=home_folder, default=None, metavar="DIR",
                   help="record frames, detections, poses, robot and alerts into DIR (replay with `monotracker replay DIR`)")
    p.add_argument("--igtl-port", type=int_range(1, 65535), default=None, metavar="PORT",
                   help="stream pose, needle, fiducials, path and status over OpenIGTLink (3D Slicer) on PORT")
    p.add_argument("--allow-remote", action="store_true",
                   help="serve OpenIGTLink on every interface (default: 127.0.0.1 only)")
    p.set_defaults(func=_demo)


def _demo(args) -> int:
    if not args.headless:
        raise InputError("the interactive demo runs in the web app; use --headless here for the terminal summary")
    from monotracker.demo.run import DemoOptions, format_report, report_json, run_demo

    opts = DemoOptions(seconds=args.seconds, trajectory=args.trajectory, fault=args.fault, fault_at_s=args.fault_at,
                       seed=args.seed, home=args.home, record=args.record,
                       igtl_port=args.igtl_port, allow_remote=args.allow_remote)
    r = run_demo(opts)
    print(report_json(r) if args.json else format_report(r))
    sys.stdout.flush()
    fr = r.get("fault_report")
    if fr is not None and (fr["standstill_at_s"] is None or not fr["plan_intact"]):
        return 1
    return 0
