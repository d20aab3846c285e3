"""The tracking loop's read side: camera, pose, robot and scene summaries for the snapshot, read
from the loop's core and its parts (:class:`~monotracker.engine.loop.core.TrackingLoop`)."""

from __future__ import annotations

from monotracker.engine.alarms import FRESHNESS_CODES
from monotracker.engine.snapshot import (
    CameraSummary,
    PoseSummary,
    RobotSummary,
    SceneGeometry,
    frozen_array,
)


def pose_summary(loop) -> PoseSummary | None:
    """``snap.pose``: the newest estimate, its verdict, and whether the loop holds for staleness."""
    rec = loop.latest
    if rec is None:
        return None
    smp = rec.sample
    now = loop.now()
    code, why = loop.holding_state()
    stale = rec.trusted and code in FRESHNESS_CODES  # the engine holds for staleness: say so
    return PoseSummary(
        t=smp.t_capture, age_s=now - smp.t_capture, ok=smp.ok, trusted=rec.trusted and not stale,
        reason=(why or "pose is stale") if stale else (rec.reason if not rec.trusted else
                                                       (smp.reason or "pose trusted")),
        T_cam_ct=frozen_array(smp.T_cam_ct), n_visible=smp.n_matched,
        fiducial_status=dict(smp.fiducial_status), residuals_px=dict(smp.residuals_px),
        fre_mm=smp.fre_mm, predicted_tre_mm=smp.predicted_tre_mm,
        latency_ms=None if smp.t_ready is None else 1000 * (smp.t_ready - smp.t_capture),
        truth_tre_mm=smp.truth_tre_mm, stale=stale, code="" if rec.trusted else rec.code,
        max_predicted_tre_mm=loop.cfg.max_predicted_tre_mm,
        validation_tre_mm={} if smp.validation is None else dict(smp.validation.errors_mm),
        validation_ok=None if smp.validation is None else bool(smp.validation.ok),
        validation_reason="" if smp.validation is None else smp.validation.reason,
        trusted_t=None if loop.last_trusted is None else loop.last_trusted.t_capture,
        averaged_frames=smp.averaged_frames, set_aside=dict(smp.set_aside),
    )


def summaries(loop):
    """``(CameraSummary, PoseSummary | None, RobotSummary, SceneGeometry)`` now."""
    cam = loop.camera
    rig = cam.rig
    times = list(cam.frame_times)
    fps = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 2 and times[-1] > times[0] else 0.0
    camera = CameraSummary(
        source=cam.source, running=bool(rig is not None and rig.running), fps=float(fps),
        K=frozen_array(None if rig is None else rig.K), dist=frozen_array(None if rig is None else rig.dist),
        image_size=None if rig is None else rig.image_size, calibration_path=cam.calibration_path,
        error=cam.error, frames=cam.frames,
    )
    pose = pose_summary(loop)
    plan = loop.plan.copy()
    last = loop.last_trusted
    T_cam_ct = None if last is None else last.T_cam_ct
    T_base_ct = None if (T_cam_ct is None or plan.T_base_cam is None) else plan.T_base_cam @ T_cam_ct
    q = T_tip = None
    tip_err = ang_err = None
    speed = 0.0
    lat = 1000 * loop.latencies_s[-1] if loop.latencies_s else None
    rob = loop.robot.rig
    if rob is not None:
        st = rob.status()
        q, T_tip, speed = st.q, st.T_base_tip, st.speed_mm_s
        if T_tip is not None and T_base_ct is not None and plan.path_complete:
            from monotracker.robot.targets import tip_and_axis_error

            tip_err, ang_err = tip_and_axis_error(T_tip, T_base_ct, plan.entry_lps_mm, plan.target_lps_mm)
        robot = RobotSummary(st.state, frozen_array(q), tip_err, ang_err, float(speed), st.connected,
                             st.message if st.program_fault else (loop.holding_reason or st.message), lat,
                             program_fault=st.program_fault, control=st.control,
                             errors_t=None if tip_err is None else last.t_capture,
                             command_t=loop.last_command_t if loop.latencies_s else None)
    else:
        state = loop.robot.state()  # "estopped" while an e-stop pressed before connecting is latched
        robot = RobotSummary(state, None, None, None, 0.0, False, "robot not connected yet" if state == "disarmed"
                             else "robot not connected yet; the e-stop is latched", None)
    scene = SceneGeometry(frozen_array(plan.T_base_cam), frozen_array(T_cam_ct), frozen_array(T_base_ct),
                          frozen_array(T_tip), frozen_array(loop.target()[0]), frozen_array(q))
    return camera, pose, robot, scene
