"""Robot control benchmark: step cost, the paper's APF-V / APF-A-I / APF-A-II comparison on the
simulated UR10, and fault injection. Prints tables; baselines are measured in the same run.

    PYTHONPATH=app python benchmarks/robot_control.py [--quick] [--rate 125]

Set-up: UR10 at the ready configuration (needle pointing down, tip ~0.55 m from the base),
needle 0.20 m, simulated arm with 8 ms command delay and 12 ms first-order joint lag, the
default safety limits (joint 1 rad/s, 3 rad/s^2; tip 0.15 m/s). Targets come from a "camera"
at 30 Hz with 50 ms capture-to-arrival latency (sample and hold), as the pose stream would
deliver them. Errors are against the *true* current target (what matters clinically).
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import sys
import time

import numpy as np

from monotracker.geometry import rotation_about_axis
from monotracker.robot import apff as apff_mod
from monotracker.robot import kinematics as kin
from monotracker.robot import lie
from monotracker.robot.apff import VARIANTS, APFFController
from monotracker.robot.head import HeadSphere
from monotracker.robot.safety import SafetyLayer, State
from monotracker.robot.sim_arm import ManualClock, SimulatedArm
from monotracker.robot.tracker import Tracker

TOOL = kin.NeedleTool()


def tip_pose(q):
    return kin.fk(q) @ TOOL.T_tool0_tip


def mm(T):
    T = np.array(T, dtype=float)
    T[:3, 3] *= 1000.0
    return T


def table(title, header, rows):
    print(f"\n{title}")
    widths = [max(len(str(h)), *(len(str(r[i])) for r in rows)) for i, h in enumerate(header)]
    line = " | ".join(str(h).ljust(w) for h, w in zip(header, widths))
    print(line)
    print("-+-".join("-" * w for w in widths))
    for r in rows:
        print(" | ".join(str(c).ljust(w) for c, w in zip(r, widths)))


# --------------------------------------------------------------------------- step cost
def step_cost(n, reference_maps=False, variant="APF-A-II"):
    """Median of per-block mean cost (us) of FK+Jacobian + controller + safety filter, with the
    head sphere active next to the needle (keep-out and repulsion code paths both run)."""
    saved = (apff_mod.exp6, apff_mod.log6, apff_mod.adjoint)
    if reference_maps:
        apff_mod.exp6, apff_mod.log6, apff_mod.adjoint = lie.exp6_ref, lie.log6_ref, lie.adjoint_ref
    try:
        k = kin.Kinematics()
        q = kin.Q_READY.copy()
        Tt = tip_pose(q)
        Tt[:3, 3] += [0.02, 0.01, 0.0]
        head = HeadSphere(Tt[:3, 3] + [0, 0, -0.095], 0.09)
        c = APFFController(variant)
        c.head = head
        s = SafetyLayer()
        s.state, s.target, s.target_received, s.target_stamp = State.TRACKING, Tt, 0.0, 0.0
        dq = np.zeros(6)
        wall, cpu = [], []
        per = max(n // 20, 1)
        for _ in range(20):
            t0, c0 = time.perf_counter(), time.process_time()
            for _ in range(per):
                T, J = k.fk_and_jacobian_body(q)
                o = c.step(T, J, dq, Tt, 0.008)
                s.filter_command(0.0, q, o.dq, 0.008, T, J, o.sigma_min, head)
            wall.append((time.perf_counter() - t0) / per * 1e6)
            cpu.append((time.process_time() - c0) / per * 1e6)
        return statistics.median(wall), min(wall), statistics.median(cpu)
    finally:
        apff_mod.exp6, apff_mod.log6, apff_mod.adjoint = saved


# --------------------------------------------------------------------------- simulation rig
class Sim:
    def __init__(self, variant, rate, q0=None, predict=False, noise_mm=0.0, noise_deg=0.0, seed=0):
        self.rate = rate
        self.clock = ManualClock()
        self.arm = SimulatedArm(q0=q0, clock=self.clock, period_s=1 / rate)
        self.tr = Tracker(arm=self.arm, clock=self.clock, variant=variant, rate_hz=rate, predict_target=predict)
        self.rng = np.random.default_rng(seed)
        self.noise_mm, self.noise_deg = noise_mm, noise_deg
        self.received = None  # last target the tracker received (truth of that capture, m)
        self.tr.safety.cfg.jump_m = 0.2  # large steps are the experiment here, not a fault
        self.tr.safety.cfg.jump_rad = 0.6
        self.cam_period = 1 / 30.0
        self.latency = 0.05
        self._next_cam = 0.0
        self._pending = []  # (arrival, stamp, T)
        self.log = []  # (t, true q, true dq, cmd, state, true target)
        self.feed = True
        self.corrupt = None

    def start(self, target_fn):
        assert self.tr.connect().ok and self.tr.arm().ok
        self.tr.set_target(mm(target_fn(0.0)), 0.0)
        r = self.tr.start_tracking()
        assert r.ok, r.reason

    def run(self, seconds, target_fn):
        n = int(round(seconds * self.rate))
        for _ in range(n):
            t = self.clock()
            if t + 1e-9 >= self._next_cam:
                self._pending.append((t + self.latency, t, target_fn(t)))
                self._next_cam += self.cam_period
            while self._pending and self._pending[0][0] <= t + 1e-9:
                _, stamp, T = self._pending.pop(0)
                if self.feed:
                    self.received = T
                    Tin = mm(T)
                    if self.noise_mm or self.noise_deg:
                        Tin[:3, 3] += self.rng.normal(0, self.noise_mm, 3)
                        ax = self.rng.normal(size=3)
                        Tin[:3, :3] = rotation_about_axis(ax, np.radians(self.rng.normal(0, self.noise_deg))) @ Tin[:3, :3]
                    if self.corrupt is not None:
                        Tin = self.corrupt(Tin)
                    self.tr.set_target(Tin, stamp)
            snap = self.tr.step()
            self.log.append((t, self.arm.true_q.copy(), self.arm.true_dq.copy(), snap.dq_cmd.copy(),
                             snap.state, target_fn(t), snap.sigma_min, self.received))
            self.clock.advance(1 / self.rate)
            self.arm.advance_to(self.clock())


def target_offset(dp=(0.05, 0.0, 0.0), rot_deg=10.0, axis=(1, 0, 0)):
    T = tip_pose(kin.Q_READY)
    T[:3, 3] += dp
    T[:3, :3] = rotation_about_axis(np.array(axis, float), np.radians(rot_deg)) @ T[:3, :3]
    return T


def errors(log, t_from=0.0):
    e_mm, e_deg, ts = [], [], []
    for t, q, _dq, _cmd, _st, Tt, *_ in log:
        if t < t_from:
            continue
        T = tip_pose(q)
        e_mm.append(np.linalg.norm(T[:3, 3] - Tt[:3, 3]) * 1000)
        e_deg.append(np.degrees(np.arccos(np.clip(T[:3, 2] @ Tt[:3, 2], -1, 1))))
        ts.append(t)
    return np.array(ts), np.array(e_mm), np.array(e_deg)


def step_response(variant, rate, seconds):
    T0 = tip_pose(kin.Q_READY)
    Tg = target_offset((0.05, 0.0, 0.0), 10.0)
    sim = Sim(variant, rate)
    sim.start(lambda t: Tg)
    sim.run(seconds, lambda t: Tg)
    ts, e, a = errors(sim.log)
    inside = (e < 0.5) & (a < 0.5)
    settle = float("nan")
    for i in range(len(ts)):
        if inside[i:].all():
            settle = ts[i]
            break
    d = (Tg[:3, 3] - T0[:3, 3]) / np.linalg.norm(Tg[:3, 3] - T0[:3, 3])
    prog = np.array([(tip_pose(q)[:3, 3] - T0[:3, 3]) @ d for _, q, *_ in sim.log])
    overshoot = max(0.0, prog.max() - np.linalg.norm(Tg[:3, 3] - T0[:3, 3])) * 1000
    dqs = np.array([x[2] for x in sim.log])
    tips = np.array([tip_pose(x[1])[:3, 3] for x in sim.log])
    v = np.diff(tips, axis=0) * rate
    acc = np.diff(v, axis=0) * rate
    jerk = np.diff(acc, axis=0) * rate
    return dict(settle=settle, overshoot=overshoot, peak_dq=np.abs(dqs).max(),
                peak_v=np.linalg.norm(v, axis=1).max() * 1000,
                jerk_rms=np.sqrt(np.mean(np.sum(jerk**2, axis=1))), final=e[-1])


def head_motion(speed_mm_s):
    """Head moving in a smooth Lissajous: x amplitude 10 mm, y 6 mm, 3 deg tilt; the peak
    translational speed is ``speed_mm_s``."""
    T0 = tip_pose(kin.Q_READY)
    w = speed_mm_s / 10.0  # rad/s so that 10 mm * w = peak x speed

    def f(t):
        T = T0.copy()
        T[:3, 3] += np.array([0.010 * np.sin(w * t), 0.006 * np.sin(0.7 * w * t), 0.0])
        T[:3, :3] = rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.radians(3.0) * np.sin(0.5 * w * t)) @ T[:3, :3]
        return T

    return f


def breathing_motion():
    """The twin's breathing head (``sim.trajectories.Breathing`` defaults): 1.5 mm along
    (0, 0.3, 1) and a 0.6 deg nod at 0.25 Hz (peak 2.4 mm/s)."""
    T0 = tip_pose(kin.Q_READY)
    d = np.array([0.0, 0.3, 1.0]) / np.linalg.norm([0.0, 0.3, 1.0])
    w = 2 * np.pi / 4.0

    def f(t):
        T = T0.copy()
        T[:3, 3] += 0.0015 * np.sin(w * t) * d
        T[:3, :3] = rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.radians(0.6) * np.sin(w * t)) @ T[:3, :3]
        return T

    return f


NOISE_MM, NOISE_DEG = 0.15, 0.05  # pose-stream jitter per frame (1 sigma)


def tracking(variant, rate, speed, seconds, predict=False):
    f = breathing_motion() if speed == "breathing" else head_motion(speed)
    sim = Sim(variant, rate, predict=predict, noise_mm=NOISE_MM, noise_deg=NOISE_DEG)
    sim.start(f)
    sim.run(seconds, f)
    _, e, a = errors(sim.log, t_from=2.0)
    # baseline: an ideal arm sitting exactly on the last (noise-free) target it has received
    floor = [np.linalg.norm(x[7][:3, 3] - x[5][:3, 3]) * 1000 for x in sim.log if x[0] >= 2.0]
    return np.sqrt(np.mean(e**2)), e.max(), np.sqrt(np.mean(a**2)), np.sqrt(np.mean(np.square(floor))), max(floor)


# --------------------------------------------------------------------------- faults
def standstill_after(log, t_fault, rate, tol=1e-3):
    """Time from the fault until the true joint speed stays below ``tol`` rad/s, and the needle
    tip path length (mm) travelled in that time."""
    idx = [i for i, x in enumerate(log) if x[0] >= t_fault]
    if not idx:
        return float("nan"), float("nan")
    i0 = idx[0]
    speeds = np.array([np.linalg.norm(x[2]) for x in log])
    stop = None
    for i in range(i0, len(log)):
        if (speeds[i:] < tol).all():
            stop = i
            break
    if stop is None:
        return float("inf"), float("nan")
    tips = np.array([tip_pose(x[1])[:3, 3] for x in log[i0:stop + 1]])
    dist = np.sum(np.linalg.norm(np.diff(tips, axis=0), axis=1)) * 1000 if len(tips) > 1 else 0.0
    return log[stop][0] - log[i0][0], dist


def fault(kind, rate, variant="APF-A-II", predict=False):
    f = head_motion(15.0)
    t_fault = 3.0
    if kind == "singular pose":
        qs = kin.Q_READY.copy()
        qs[4] = -0.35

        def f(t):  # drives the wrist through q5 = 0 from t = 1 s
            q = qs.copy()
            q[4] = -0.35 + min(max(t - 1.0, 0.0), 4.0) * 0.15
            return tip_pose(q)

        sim = Sim(variant, rate, q0=qs, predict=predict)
        sim.start(f)
        sim.run(7.0, f)
        hold = [x[0] for x in sim.log if x[4] == "holding"]
        t0 = hold[0] if hold else float("nan")
        smin = min(x[6] for x in sim.log if np.isfinite(x[6]))
        tstop, dist = standstill_after(sim.log, t0, rate) if hold else (float("nan"), float("nan"))
        reason = sim.tr.safety.history[-1].reason
        return sim.tr.state.value, tstop, dist, f"{reason}; min sigma {smin:.4f}"
    sim = Sim(variant, rate, predict=predict)
    sim.start(f)
    sim.run(t_fault, f)
    if kind == "stale target":
        sim.feed = False
    elif kind == "target jump":
        def jump(T):
            T = T.copy()
            T[0, 3] += 50.0
            return T
        sim.corrupt = jump
        sim.tr.safety.cfg.jump_m = 0.02
    elif kind == "NaN pose":
        def nan(T):
            T = T.copy()
            T[1, 3] = np.nan
            return T
        sim.corrupt = nan
    elif kind == "arm disconnect":
        sim.arm.drop_connection()
    sim.run(3.0, f)
    tstop, dist = standstill_after(sim.log, t_fault, rate)
    return sim.tr.state.value, tstop, dist, sim.tr.safety.history[-1].reason


def prediction_event(kind, rate, predict, variant="APF-A-II"):
    """A head moving at 15 mm/s that jumps 6 mm at t = 3 s (a real jump under the tracker's 20 mm
    limit) or is occluded 0.3 s from t = 3 s: the worst tip error (mm) vs the true head in the
    1.5 s after the event, the worst error in the 1 s before it, and how far the tip went beyond
    the head's new position along the jump (overshoot, mm; jump only)."""
    base = head_motion(15.0)
    jump = np.array([0.006, 0.0, 0.0]) if kind == "jump" else np.zeros(3)

    def f(t):
        T = base(t).copy()
        if t >= 3.0:
            T[:3, 3] += jump
        return T

    sim = Sim(variant, rate, predict=predict, noise_mm=NOISE_MM, noise_deg=NOISE_DEG)
    sim.start(f)
    sim.run(3.0, f)
    if kind == "occlusion":
        sim.feed = False
        sim.run(0.3, f)
        sim.feed = True
    sim.run(1.5 if kind == "jump" else 1.2, f)
    ts, e, _ = errors(sim.log)
    before = e[(ts >= 2.0) & (ts < 3.0)].max()
    after = e[ts >= 3.0].max()
    over = float("nan")
    if kind == "jump":
        d = jump / np.linalg.norm(jump)
        over = max(float((tip_pose(x[1])[:3, 3] - x[5][:3, 3]) @ d) * 1000 for x in sim.log if x[0] >= 3.0)
        over = max(0.0, over)
    states = {x[4] for x in sim.log if x[0] >= 3.0}
    return before, after, over, sim.tr.state.value, ",".join(sorted(states))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter runs (smoke test)")
    ap.add_argument("--rate", type=float, default=125.0, help="control rate, Hz (125 CB3, 500 e-Series)")
    a = ap.parse_args(argv)
    t_start = time.perf_counter()
    n_cost = 2000 if a.quick else 10000
    t_step = 3.0 if a.quick else 5.0
    t_track = 8.0 if a.quick else 20.0
    rate = a.rate
    # Sections 2-4 track without a head sphere on purpose (free space); the tracker's warning
    # about that would otherwise print once per run. Errors still print.
    logging.getLogger("monotracker.robot").setLevel(logging.ERROR)
    print(f"MonoTracker robot control benchmark  (rate {rate:.0f} Hz, python {sys.version.split()[0]}, "
          f"{'quick' if a.quick else 'full'}; sections 2-4 run without a head sphere)")

    rows = []
    for v in VARIANTS:
        med, best, cpu = step_cost(n_cost, False, v)
        rows.append([v, "pinocchio C++ lie maps (ours)", f"{med:.1f}", f"{best:.1f}", f"{cpu:.1f}",
                     "yes" if cpu <= 200 else "NO"])
    med, best, cpu = step_cost(n_cost, True, "APF-A-II")
    rows.append(["APF-A-II", "baseline: numpy reference lie maps", f"{med:.1f}", f"{best:.1f}", f"{cpu:.1f}",
                 "yes" if cpu <= 200 else "NO"])
    rows.append(["APF-A-II", "paper (reported, per iteration)", "39300", "-", "-", "NO"])
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    table(f"1. Control step cost: FK + body Jacobian + APFF + safety filter, head sphere active "
          f"(us per step; target <= 200 us; {os.cpu_count()} CPUs, load average {load:.1f})",
          ["variant", "implementation", "wall median", "wall best block", "CPU median", "<= 0.2 ms (CPU)"], rows)

    rows = []
    for v in VARIANTS:
        r = step_response(v, rate, t_step)
        rows.append([v, f"{r['settle']:.2f}" if np.isfinite(r["settle"]) else "not settled", f"{r['overshoot']:.2f}",
                     f"{r['peak_dq']:.3f}", f"{r['peak_v']:.0f}", f"{r['jerk_rms']:.2f}", f"{r['final']:.3f}"])
    table("2. Step response: 50 mm + 10 deg step of the needle target (settled: within 0.5 mm and 0.5 deg for good)",
          ["variant", "settling s", "overshoot mm", "peak joint rad/s", "peak tip mm/s", "tip jerk RMS m/s^3", "final err mm"], rows)

    rows = []
    for speed in ("breathing", 5.0, 15.0, 30.0):
        label = speed if isinstance(speed, str) else f"{speed:.0f}"
        for i, (v, pred) in enumerate([(x, False) for x in VARIANTS] + [("APF-A-II", True)]):
            rms, mx, ang, frms, fmax = tracking(v, rate, speed, t_track, pred)
            if i == 0:
                rows.append([label, "baseline: ideal arm on the last received target", f"{frms:.2f}", f"{fmax:.2f}", "-"])
            name = v + (" + latency prediction (engine default)" if pred else "")
            if v == "APF-A-II" and not pred:
                name += " (paper; old engine default)"
            rows.append([label, name, f"{rms:.2f}", f"{mx:.2f}", f"{ang:.2f}"])
    table(f"3. Tracking a moving head (camera 30 Hz, 50 ms latency, pose jitter {NOISE_MM} mm / {NOISE_DEG} deg; "
          "error vs the true current target, after 2 s; goal with prediction: 15 mm/s <= 0.5 mm RMS, "
          "breathing <= 0.3 mm)",
          ["head peak mm/s", "variant", "tip RMS mm", "tip max mm", "axis RMS deg"], rows)

    rows = []
    for kind in ("stale target", "target jump", "NaN pose", "arm disconnect", "singular pose"):
        for pred in (False, True):
            st, tstop, dist, reason = fault(kind, rate, predict=pred)
            rows.append([kind, "on (default)" if pred else "off (old default)", st, f"{tstop:.3f}",
                         f"{dist:.2f}", reason])
    table("4. Fault injection while tracking a head moving at 15 mm/s (APF-A-II): time from the fault to "
          "standstill (< 1e-3 rad/s) and needle-tip distance travelled meanwhile",
          ["fault", "prediction", "final state", "to standstill s", "travelled mm", "reason logged"], rows)

    rows = []
    for kind in ("jump", "occlusion"):
        for pred in (False, True):
            before, after, over, st, states = prediction_event(kind, rate, pred)
            rows.append([kind, "on (default)" if pred else "off (old default)", f"{before:.2f}", f"{after:.2f}",
                         "-" if not np.isfinite(over) else f"{over:.2f}", states, st])
    table("5. Prediction under a real 6 mm head jump (accepted: under the 20 mm limit) and a 0.3 s occlusion, "
          "head at 15 mm/s: worst tip error before (1 s) and after (1.5 s) the event, overshoot beyond the "
          "jumped head along the jump",
          ["event", "prediction", "max err before mm", "max err after mm", "overshoot mm", "states after", "final"],
          rows)
    print(f"\ntotal wall time {time.perf_counter() - t_start:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
