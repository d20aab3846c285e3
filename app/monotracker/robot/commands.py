"""``monotracker calibrate-handeye`` and ``monotracker robot-check``."""

from __future__ import annotations

import json
import pathlib

import numpy as np

from monotracker.cli_args import finite_float, ip_address
from monotracker.errors import InputError, MonoTrackerError


def register(sub) -> None:
    p = sub.add_parser("calibrate-handeye", help="eye-to-hand calibration: camera pose in the robot base frame")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--simulate", action="store_true", help="run a simulated calibration (UR10 twin + virtual camera)")
    src.add_argument("--poses", type=pathlib.Path,
                     help="JSON with 'T_base_tool0_mm' and 'T_cam_target_mm' (lists of 4x4, mm)")
    p.add_argument("--n", type=int, default=15, help="simulated poses (default 15)")
    p.add_argument("--noise-px", type=float, default=0.2, help="simulated pixel noise (default 0.2)")
    p.add_argument("--method", default="best", help="best (default), tsai, park, horaud, andreff, daniilidis")
    p.add_argument("--out", type=pathlib.Path, default=None, help="where to save the result JSON")
    p.set_defaults(func=_calibrate)

    c = sub.add_parser("robot-check", help="connect to a UR through RTDE and print its joint state (no motion)")
    c.add_argument("host", type=ip_address, help="robot IP address (no host names: nothing is looked up)")
    c.add_argument("--rate", type=finite_float(1.0, 500.0), default=125.0, help="RTDE frequency, Hz (500 for e-Series)")
    c.set_defaults(func=_check)


def _calibrate(args) -> int:
    from monotracker.geometry import rotation_angle_deg
    from monotracker.robot.handeye import calibrate_eye_to_hand, save_handeye, simulate_calibration

    truth = None
    if args.simulate:
        if args.n < 3:
            raise InputError("--n must be at least 3")
        sim = simulate_calibration(args.n, pixel_noise=args.noise_px)
        A, B, truth = sim.T_base_tool0_mm, sim.T_cam_target_mm, sim.T_base_cam_mm
    else:
        try:
            data = json.loads(args.poses.read_text(encoding="utf-8"))
            A, B = data["T_base_tool0_mm"], data["T_cam_target_mm"]
        except FileNotFoundError:
            raise InputError(f"poses file not found: {args.poses}") from None
        except (ValueError, KeyError, TypeError):
            raise InputError(f"{args.poses}: expected JSON with 'T_base_tool0_mm' and 'T_cam_target_mm'") from None
    res = calibrate_eye_to_hand(A, B, method=args.method)
    if not res.ok:
        raise MonoTrackerError(res.reason)
    print(res.reason)
    print("T_base_cam_mm =")
    print(np.array2string(res.T_base_cam_mm, precision=3, suppress_small=True))
    if truth is not None:
        print(f"error vs simulated truth: {np.linalg.norm(res.T_base_cam_mm[:3, 3] - truth[:3, 3]):.2f} mm, "
              f"{rotation_angle_deg(res.T_base_cam_mm[:3, :3], truth[:3, :3]):.3f} deg")
    if args.out:
        print(f"saved {save_handeye(res, args.out)}")
    return 0


def _check(args) -> int:
    from monotracker.robot.arm import ArmError
    from monotracker.robot.ur_rtde_arm import read_joint_state

    try:  # receive interface only: opening the control interface would stop the robot's program
        st = read_joint_state(args.host, rate_hz=args.rate)
    except ArmError as exc:
        raise MonoTrackerError(str(exc)) from None
    print("q (deg):", np.array2string(np.degrees(st.q), precision=2))
    return 0
