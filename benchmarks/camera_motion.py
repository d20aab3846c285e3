"""The camera moving after the hand-eye calibration: what it costs and what the background watch sees (issue 36).

The twin camera (OR layout, 450 mm from the fiducial patch, f = 1100 px) is moved in the room
(``sim.faults.CameraMotion``; the drape behind the head is a room-fixed plane) while the head
moves; ``vision.camera_motion.CameraMotionMonitor`` (the default settings, one check every 3rd
frame) watches the frames.

1. **Knocks** of several sizes (rotation about the bump axis, no shift, and the fault's 1.5 deg
   + 3 mm): the error the arm would follow at the planned target (rotation x camera-to-target
   distance; the baseline: today nothing notices), whether the monitor called it moved, and after
   how long.
2. **Sag** at several rates: time from onset to the alarm, the camera's turn then, and the error
   at the target at that moment.
3. **False alarms**: a still camera, head trajectories still / breathing / drift / jumps / mixed,
   with scripted events (hands and instruments sweeping over the balls, strays, lighting
   changes) and photo-like frames: alarms, checks made, largest background shift (px) and its
   95th percentile.
4. Cost per check (ms, median / p95) at the load printed.

Usage: PYTHONPATH=app python benchmarks/camera_motion.py [--quick]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from monotracker.geometry import apply_transform
from monotracker.sim.camera_sim import SimulatedCamera, random_events
from monotracker.sim.faults import CameraMotion
from monotracker.sim.or_layout import default_layout
from monotracker.sim.trajectories import make_trajectory
from monotracker.vision.camera_motion import CameraMotionMonitor
from monotracker.vision.frames import Frame
from monotracker.vision.pose_tracker import PoseTracker

LAYOUT = default_layout()
PH = LAYOUT.phantom
TARGET_DISTANCE_MM = float(np.linalg.norm(apply_transform(LAYOUT.T_cam_ct0, PH.sample_target_lps)))


def camera(trajectory: str, seed: int, events_s: float = 0.0, optics=None) -> SimulatedCamera:
    cam = SimulatedCamera(seed=seed, trajectory=make_trajectory(trajectory, seed=seed), T_cam_world=LAYOUT.T_cam_ct0,
                          optics=optics)
    if events_s:
        cam.events = random_events(events_s, cam.rest_projection(), seed=seed + 2)
    return cam


def run(cam: SimulatedCamera, seconds: float, stop_when_moved: bool = True):
    """(monitor, [(t, report)], [check cost s])."""
    mon = CameraMotionMonitor(float(cam.camera.K[0, 0]))
    out, cost = [], []
    for i in range(int(seconds * cam.fps)):
        t = i / cam.fps
        img, truth = cam.render(t)
        t0 = time.perf_counter()
        rep = mon.update(img, truth.ellipse_centres_px)
        if rep is not None:
            cost.append(time.perf_counter() - t0)
            out.append((t, rep))
            if rep.moved and stop_when_moved:
                break
    return mon, out, cost


def baseline_after(cam: SimulatedCamera, t_from: float, seconds: float):
    """Today's pipeline (no background watch) on the same moved camera's frames from ``t_from``:
    (trusted share, median error at the planned target in the camera frame the hand-eye was
    calibrated in, mm). The pose is right relative to the moved camera; the arm maps it through
    the old camera pose, so its target is off by the camera's motion."""
    trk = PoseTracker(PH.fiducial_centres_lps, cam.camera, radius_mm=PH.fiducial_radius_mm,
                      target_ct=PH.sample_target_lps)
    trusted, errs, n = 0, [], 0
    for i in range(int(seconds * cam.fps)):
        t = i / cam.fps
        img, truth = cam.render(t)
        est = trk.process(Frame(img, t, i, truth))
        if t < t_from:
            continue
        n += 1
        if est.ok:
            trusted += 1
            T_rest = cam.T_cam_world @ cam.trajectory.pose(t)      # where the arm believes the camera is
            errs.append(float(np.linalg.norm(apply_transform(est.T_cam_ct, PH.sample_target_lps)
                                             - apply_transform(T_rest, PH.sample_target_lps))))
    return trusted / max(n, 1), (float(np.median(errs)) if errs else float("nan"))


def table_knocks(seeds: int) -> list:
    print(f"\n1. Knocks at t = 0.5 s (camera to target {TARGET_DISTANCE_MM:.0f} mm), breathing head; {seeds} seeds")
    print("   baseline (same frames, today's pipeline without the watch): share of poses after the knock still "
          "trusted, and their error at the target")
    print(f"{'knock':>16} {'rot x dist mm':>13} {'baseline: trusted':>17} {'err mm':>7} {'watch: caught':>13} "
          f"{'after s (max)':>13}")
    costs = []
    for deg, mm in ((0.05, 0.0), (0.1, 0.0), (0.15, 0.0), (0.2, 0.0), (0.3, 0.0), (0.5, 0.0), (1.5, 3.0)):
        caught, delays, shares, berrs = 0, [], [], []
        for s in range(seeds):
            cam = camera("breathing", 10 + s)
            cam.camera_motion = CameraMotion("camera-bump", 0.5, bump_deg=deg, bump_mm=mm)
            mon, out, cost = run(cam, 1.5)
            costs += cost
            if mon.moved:
                caught += 1
                delays.append(out[-1][0] - 0.5)
            cam2 = camera("breathing", 10 + s)
            cam2.camera_motion = CameraMotion("camera-bump", 0.5, bump_deg=deg, bump_mm=mm)
            share, berr = baseline_after(cam2, 0.5, 1.5)
            shares.append(share)
            berrs.append(berr)
        err = np.radians(deg) * TARGET_DISTANCE_MM + mm
        d = f"{max(delays):13.2f}" if delays else f"{'-':>13}"
        print(f"{f'{deg:g} deg + {mm:g} mm':>16} {err:13.2f} {100 * np.mean(shares):16.0f}% {np.nanmedian(berrs):7.2f} "
              f"{caught:>9}/{seeds:<3} {d}")
    return costs


def table_sag(seeds: int) -> list:
    print("\n2. Sag from t = 0.3 s, breathing head")
    print(f"{'rate deg/s':>10} {'caught':>7} {'after s (mean)':>14} {'turn then deg':>13} {'error at target then mm':>23}")
    costs = []
    for rate in (0.02, 0.05, 0.1, 0.3):
        caught, delays, turns = 0, [], []
        for s in range(seeds):
            cam = camera("breathing", 20 + s)
            sag = CameraMotion("camera-sag", 0.3, sag_deg_per_s=rate)
            cam.camera_motion = sag
            mon, out, cost = run(cam, 0.3 + min(0.4 / rate, 12.0))
            costs += cost
            if mon.moved:
                caught += 1
                delays.append(out[-1][0] - 0.3)
                turns.append(sag.angle_deg(out[-1][0]))
        if turns:
            print(f"{rate:10g} {caught:>3}/{seeds:<3} {np.mean(delays):14.2f} {np.mean(turns):13.3f} "
                  f"{np.radians(np.mean(turns)) * TARGET_DISTANCE_MM:23.2f}")
        else:
            print(f"{rate:10g} {caught:>3}/{seeds:<3}")
    return costs


def table_false_alarms(seconds: float, seeds: int) -> list:
    print(f"\n3. A still camera ({seconds:g} s per run, {seeds} seeds): false alarms")
    print(f"{'trajectory':>10} {'events':>6} {'optics':>7} {'alarms':>7} {'checks':>7} {'not checking':>12} "
          f"{'shift max px':>12} {'p95':>6}")
    costs = []
    for traj, events, optics in (("still", False, None), ("breathing", True, None), ("drift", True, None),
                                 ("jumps", True, None), ("mixed", True, None), ("mixed", True, "photo")):
        alarms = checks = blind = 0
        shifts = []
        for s in range(seeds):
            cam = camera(traj, 30 + s, seconds if events else 0.0, optics)
            secs = seconds if optics is None else seconds / 3
            mon, out, cost = run(cam, secs, stop_when_moved=False)
            costs += cost
            alarms += mon.moved
            checks += len(out)
            blind += sum(not r.checking for _t, r in out)
            shifts += [r.shift_px for _t, r in out if r.checking]
        print(f"{traj:>10} {'yes' if events else 'no':>6} {optics or 'simple':>7} {alarms:>3}/{seeds:<3} {checks:7d} "
              f"{blind:12d} {np.max(shifts):12.2f} {np.percentile(shifts, 95):6.2f}")
    return costs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    seeds, seconds = (1, 6.0) if args.quick else (3, 20.0)
    print(f"load before: {os.getloadavg()[0]:.2f}")
    t0 = time.perf_counter()
    costs = table_knocks(seeds) + table_sag(seeds) + table_false_alarms(seconds, seeds)
    c = 1000 * np.array(costs)
    print(f"\n4. cost per check: median {np.median(c):.2f} ms, p95 {np.percentile(c, 95):.2f} ms "
          f"({len(c)} checks; one check every 3rd frame); load after: {os.getloadavg()[0]:.2f}; "
          f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
