"""A whole surgical session without a browser: CT, fiducials, plan, camera, arm, tracking.

What it shows: the engine's :class:`monotracker.engine.Session`, the same object the web app
drives, on a simulated clock (``clock="sim"``: camera, registration and the 125 Hz control run in
lock-step, so the run is repeatable on any machine). It loads the sample CT, confirms the
detected fiducials, plans the sample path, starts the simulated camera, arms with the PIN,
tracks a breathing head for a few seconds, and prints the needle tip error against the truth;
then it exports fiducials and path as 3D Slicer markups (``.mrk.json``, LPS) and shows the audit
log. Every command returns ``CommandResult(ok, message)`` and never raises for operator
mistakes. The session's files (plan, audit log) go to a temporary folder (removed at the end) unless
``--home``.

Run: ``python examples/06_headless_session.py [--seconds 3] [--home DIR]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from monotracker.engine import Session, SessionConfig


def need(result, what: str):
    """Stop the example with the engine's own one-line reason when a step is refused."""
    if not result.ok:
        raise SystemExit(f"{what} refused: {result.message}")
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--home", help="folder for plan.json and audit.sqlite (default: a temporary folder, "
                                   "removed at the end)")
    args = ap.parse_args(argv)
    if args.home:
        return run(Path(args.home), args.seconds)
    with tempfile.TemporaryDirectory(prefix="monotracker-example-") as home:
        return run(Path(home), args.seconds)


def run(home: Path, seconds: float) -> int:
    s = Session(SessionConfig(home=home, clock="sim", camera="sim", robot="sim", arm_pin="2468",
                              trajectory="breathing"))
    try:
        need(s.load_sample_ct(), "load CT")
        job = s.wait_for_job(180)
        if job is None or job.error:
            raise SystemExit(f"CT failed: {None if job is None else job.error}")
        snap = s.snapshot()
        print(f"CT {snap.ct.shape} voxels; {len(snap.fiducials)} fiducials detected")
        for f in snap.fiducials:                     # an OR technician would look at each one
            need(s.set_fiducial_status(f.id, "confirmed"), f"confirm fiducial {f.id}")
        need(s.confirm_fiducials(), "lock fiducials")
        need(s.use_sample_plan(), "plan")
        plan = s.snapshot().plan
        print(f"path {plan.path_length_mm:.1f} mm long, {plan.distance_to_fiducials_mm:.1f} mm from the nearest fiducial")

        need(s.start_camera(), "camera")
        for _ in range(100):                          # up to 5 s of simulated time for a trusted pose
            s.advance(0.05)
            pose = s.snapshot().pose
            if pose is not None and pose.trusted:
                break
        else:
            raise SystemExit("no trusted pose within 5 s")
        print(f"pose trusted: {pose.n_visible} fiducials, FRE {pose.fre_mm:.2f} mm, "
              f"predicted TRE {pose.predicted_tre_mm:.2f} mm")
        print("wrong PIN:", s.arm("0000").message)
        need(s.arm("2468"), "arm")
        need(s.start_tracking(), "start tracking")
        errors = []
        t_end = s.snapshot().t + seconds
        while s.snapshot().t < t_end:
            s.advance(0.1)
            r = s.snapshot().robot
            errors.append(r.tip_error_mm)
        r = s.snapshot().robot
        settled = [e for e in errors[len(errors) // 2:] if e is not None]
        print(f"robot {r.state}; needle tip to the tracked entry, second half {min(settled):.2f}-{max(settled):.2f} mm")
        need(s.stop_tracking(), "stop tracking")
        need(s.disarm(), "disarm")

        files = s.export_slicer_markups(home / "slicer")
        print("3D Slicer markups:", ", ".join(str(p) for p in files))
        print("last audit entries:")
        for e in s.audit_entries()[-5:]:
            print(f"  [{e.level}] {e.code}: {e.message}")
        return 0 if settled and max(settled) < 2.0 else 1
    finally:
        s.shutdown()


if __name__ == "__main__":
    sys.exit(main())
