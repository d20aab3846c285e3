"""Offline replay of a session recording: re-run detection + registration, compare the poses.

``replay_recording(folder) -> ReplayReport`` reads a closed recording (refused with one line when it
is incomplete or corrupt, see :mod:`monotracker.vision.replay_source`), rebuilds for every camera
segment the estimator the session ran (``"image"`` frames: vision's :class:`PoseTracker` with the
recorded calibration, classical detector, fiducials and target; ``"points"`` frames: the twin's
point-level rig), feeds it the recorded frames in order with their recorded frame index and capture
time (the tracker's prior logic depends on both), and compares each replayed pose with the recorded
one at the planned target: ``|T_replayed @ target - T_recorded @ target|`` in mm.

A frame counts as a mismatch when one run found a pose and the other did not. Frames recorded while
the ``bad-pose`` fault was injected are skipped (the recorded pose was corrupted on purpose after
estimation); camera-fault rows (frozen/stalled) are replayed as faults (they reset the tracker's
prior, as they did live). Exactness: on the same program and library versions (the manifest records
them) the replay reproduces poses to ~1e-9 mm; a recording begun while the camera was already
running (``mid_stream``) may differ on its first frames (the live tracker had a prior).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from monotracker.errors import InputError
from monotracker.geometry import apply_transform
from monotracker.vision.replay_source import load_frame_image, read_frame_index, read_jsonl, read_manifest

DEFAULT_TOLERANCE_MM = 1e-3


@dataclass
class ReplayReport:
    """``frames``: frames whose poses were compared (both runs have a pose); ``max_pose_diff_mm`` /
    ``mean_pose_diff_mm`` at the target (None when nothing was compared); ``ok_mismatches`` frames
    where exactly one run found a pose; ``skipped`` frames not compared, by reason; ``ok`` all within
    ``tolerance_mm`` and no mismatch; ``reason`` one line."""

    recording: str
    frames: int
    max_pose_diff_mm: float | None
    mean_pose_diff_mm: float | None
    ok_mismatches: int
    frames_total: int
    skipped: dict = field(default_factory=dict)
    tolerance_mm: float = DEFAULT_TOLERANCE_MM
    ok: bool = False
    reason: str = ""
    versions_recorded: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)

    def to_json(self) -> str:
        return json.dumps(asdict(self))


def _load_json(path: Path) -> dict:
    if not path.is_file():
        raise InputError(f"recording is incomplete: {path.name} is missing")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"recording file {path.name} is unreadable ({exc})") from None


class _ImageEstimator:
    """What SimImageRig / StreamRig ran: vision's PoseTracker (classical detector)."""

    def __init__(self, folder: Path, seg: dict):
        from monotracker.vision.camera_model import CameraModel
        from monotracker.vision.pose_stream import PoseTracker

        if not seg.get("calibration"):
            raise InputError(f"recording segment {seg['segment']} has no camera calibration")
        cam = CameraModel.load(folder / seg["calibration"])
        target = seg.get("target_lps_mm")
        self.tracker = PoseTracker(np.asarray(seg["fiducials_lps_mm"], float), cam, radius_mm=float(seg["radius_mm"]),
                                   target_ct=None if target is None else np.asarray(target, float))
        self.folder = folder

    def run(self, row: dict):
        from monotracker.vision.frames import Frame

        if row["kind"] == "fault":
            self.tracker.camera_fault(int(row["index"]), float(row["t_capture"]), row.get("camera", "stalled"),
                                      "camera fault (recorded)")
            return None, False
        img = load_frame_image(self.folder, row)
        est = self.tracker.process(Frame(img, float(row["t_capture"]), int(row["index"])))
        return est.T_cam_ct, bool(est.ok)


class _PointEstimator:
    """What the "sim-points" rig ran: its own estimate() on the recorded points."""

    def __init__(self, folder: Path, seg: dict, plan_dict: dict):
        from monotracker.engine.plan import plan_from_dict
        from monotracker.engine.rigs.sim import ProjectedFiducialRig
        from monotracker.vision.camera_model import CameraModel

        plan = plan_from_dict(plan_dict)
        plan.fiducials = [f for f in plan.fiducials if f.id in set(seg["fiducial_ids"])]
        for f in plan.fiducials:
            f.status = "confirmed"
        if seg.get("target_lps_mm") is not None:
            plan.target_lps_mm = np.asarray(seg["target_lps_mm"], float)
        self.rig = ProjectedFiducialRig(plan)
        self.rig.fiducials_ct = np.asarray(seg["fiducials_lps_mm"], float)
        self.rig.radius_mm = float(seg["radius_mm"])
        if seg.get("calibration"):
            cam = CameraModel.load(folder / seg["calibration"])
            self.rig.K, self.rig.dist = cam.K, cam.dist

    def run(self, row: dict):
        from monotracker.engine.rigs.sim import SimFrame

        pts = np.asarray(row.get("points_px") or [], float).reshape(-1, 2)
        minor = row.get("minor_px")  # the balls' image sizes (px); older recordings have none
        minor = None if minor is None or len(minor) != len(pts) else np.asarray(minor, float)
        frame = SimFrame(float(row["t_capture"]), int(row["index"]), np.eye(4), pts, np.arange(len(pts)), minor)
        smp = self.rig.estimate(frame)
        return smp.T_cam_ct, bool(smp.ok)


def replay_recording(folder: str | Path, tolerance_mm: float = DEFAULT_TOLERANCE_MM) -> ReplayReport:
    """Replay ``folder`` (see the module docstring). Raises :class:`InputError` (one line) for a
    recording that is not complete and intact."""
    folder = Path(folder)
    m = read_manifest(folder)
    rows = read_frame_index(folder, m)
    poses = read_jsonl(folder / "poses.jsonl")
    if len(poses) != len(rows) or any(p.get("seq") != r["seq"] for p, r in zip(poses, rows)):
        raise InputError(f"recording {folder} is corrupt: poses.jsonl does not match frames.jsonl row for row")
    plan_dict = _load_json(folder / "plan.json")
    segments = {int(s["segment"]): s for s in m.get("segments", [])}
    notes = []
    estimator = None
    current = None
    diffs: list[float] = []
    mismatches = 0
    skipped: dict[str, int] = {}
    for row, pose in zip(rows, poses):
        seg_no = int(row["segment"])
        if seg_no != current:
            seg = segments.get(seg_no)
            if seg is None:
                raise InputError(f"recording is corrupt: frame {row['seq']} is in segment {seg_no}, "
                                 "which the manifest does not describe")
            if seg.get("mid_stream"):
                notes.append(f"segment {seg_no} began while the camera was already running: its first "
                             "frames may differ (the live tracker had a prior)")
            kind = row["kind"] if row["kind"] != "fault" else next(
                (r["kind"] for r in rows if int(r["segment"]) == seg_no and r["kind"] != "fault"), "image")
            estimator = _PointEstimator(folder, seg, plan_dict) if kind == "points" else _ImageEstimator(folder, seg)
            current = seg_no
            target = seg.get("target_lps_mm")
        if row["kind"] == "none":
            skipped["no frame recorded"] = skipped.get("no frame recorded", 0) + 1
            continue
        T_rep, ok_rep = estimator.run(row)
        if pose.get("fault") == "bad-pose":
            skipped["bad-pose fault injected"] = skipped.get("bad-pose fault injected", 0) + 1
            continue
        if row["kind"] == "fault":
            skipped["camera fault"] = skipped.get("camera fault", 0) + 1
            continue
        ok_rec = bool(pose.get("ok")) and pose.get("T_cam_ct") is not None
        if ok_rep != ok_rec:
            mismatches += 1
            continue
        if not ok_rec:
            skipped["no pose in either run"] = skipped.get("no pose in either run", 0) + 1
            continue
        if target is None:
            skipped["no planned target"] = skipped.get("no planned target", 0) + 1
            continue
        tgt = np.asarray(target, float)
        d = apply_transform(np.asarray(T_rep, float), tgt) - apply_transform(np.asarray(pose["T_cam_ct"], float), tgt)
        diffs.append(float(np.linalg.norm(d)))
    mx = max(diffs) if diffs else None
    mean = float(np.mean(diffs)) if diffs else None
    if not diffs:
        ok, reason = False, "no frame with a pose to compare"
    elif mismatches:
        ok, reason = False, f"{mismatches} frames found a pose in one run but not the other"
    elif mx > tolerance_mm:
        ok, reason = False, f"poses differ by up to {mx:.3g} mm at the target (tolerance {tolerance_mm:g} mm)"
    else:
        ok, reason = True, f"{len(diffs)} poses reproduced within {tolerance_mm:g} mm (max {mx:.2g} mm)"
    return ReplayReport(recording=str(folder), frames=len(diffs), max_pose_diff_mm=mx, mean_pose_diff_mm=mean,
                        ok_mismatches=mismatches, frames_total=len(rows), skipped=skipped, tolerance_mm=tolerance_mm,
                        ok=ok, reason=reason, versions_recorded=m.get("versions", {}), notes=notes)


def format_report(r: ReplayReport) -> str:
    lines = [f"replay of {r.recording}: {r.frames_total} frames recorded, {r.frames} poses compared",
             "  max / mean pose difference at the target: "
             + ("n/a" if r.max_pose_diff_mm is None else f"{r.max_pose_diff_mm:.3g} / {r.mean_pose_diff_mm:.3g} mm"),
             f"  found a pose in one run only: {r.ok_mismatches}"]
    for why, n in r.skipped.items():
        lines.append(f"  not compared ({why}): {n}")
    lines += [f"  note: {n}" for n in r.notes]
    lines.append(f"  {'OK' if r.ok else 'FAILED'}: {r.reason}")
    return "\n".join(lines)


__all__ = ["ReplayReport", "replay_recording", "format_report", "DEFAULT_TOLERANCE_MM"]
