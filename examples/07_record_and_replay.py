"""Record a session, then replay it: re-run detection + registration on the recorded frames.

What it shows: the headless demo (the engine ``Session`` on a simulated clock, rendered camera,
simulated UR10) run with a recording folder (``monotracker.engine.recording``: lossless PNG
frames, detections, poses, robot state, targets, alerts, the plan and the calibration, with a
``manifest.json``), then :func:`monotracker.interop.replay.replay_recording`, which runs today's
detection + registration again on every recorded frame and compares the poses at the planned
target. A change to the pipeline that moves a pose shows up as ``max_pose_diff_mm``; this is how
a recorded real session checks our numbers. Exits non-zero if the replay disagrees by more than
1e-3 mm. The recording goes to a temporary folder unless ``--out``.

Run: ``python examples/07_record_and_replay.py [--seconds 2] [--out DIR]``
(the same from the shell: ``monotracker demo --headless --seconds 2 --record DIR`` then
``monotracker replay DIR --json``)
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from monotracker.demo.run import DemoOptions, run_demo
from monotracker.interop.replay import format_report, replay_recording


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--out", help="recording folder (default: a temporary folder, removed at the end)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="monotracker-example-") as tmp:    # ~90 MB: not left behind
        work = Path(tmp)
        rec = Path(args.out) if args.out else work / "recording"
        r = run_demo(DemoOptions(seconds=args.seconds, home=work / "home", record=rec))
        print(f"recorded {r['frames']} frames of a {args.seconds:.0f} s tracking run into {rec}")
        print("files:", ", ".join(sorted(p.name for p in rec.iterdir() if p.is_file())))
        report = replay_recording(rec, tolerance_mm=1e-3)
        print(format_report(report))
        return 0 if report.ok and report.frames > 0 else 1


if __name__ == "__main__":
    sys.exit(main())
