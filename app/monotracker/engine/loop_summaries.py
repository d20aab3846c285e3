"""The tracking loop's read side: camera, pose, robot and scene summaries for the snapshot.

Mixed into :class:`~monotracker.engine.loop.TrackingLoop`, whose state these methods read."""

from __future__ import annotations

from monotracker.engine.alarms import FRESHNESS_CODES
from monotracker.engine.snapshot import (
    CameraSummary,
    PoseSummary,
    RobotSummary,
    SceneGeometry,
    frozen_array,
)


class LoopSummaries:
    """The tracking loop's read side: camera, pose, robot and scene summaries for the snapshot (part of :class:`~monotracker.engine.loop.TrackingLoop`)."""

    def pose_summary(self) -> PoseSummary | None:
        rec = self._latest
        if rec is None:
            return None
        smp = rec.sample
        now = self.now()
        with self._lock:
            code, why = self._holding_code, self._holding_reason
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
            max_predicted_tre_mm=self.cfg.max_predicted_tre_mm,
            validation_tre_mm={} if smp.validation is None else dict(smp.validation.errors_mm),
            validation_ok=None if smp.validation is None else bool(smp.validation.ok),
            validation_reason="" if smp.validation is None else smp.validation.reason,
        )

    def summaries(self):
        rig = self.rig
        times = list(self._frame_times)
        fps = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 2 and times[-1] > times[0] else 0.0
        cam = CameraSummary(
            source=self.camera_source, running=bool(rig is not None and rig.running), fps=float(fps),
            K=frozen_array(None if rig is None else rig.K), dist=frozen_array(None if rig is None else rig.dist),
            image_size=None if rig is None else rig.image_size, calibration_path=self.calibration_path,
            error=self.camera_error, frames=self._frames,
        )
        pose = self.pose_summary()
        plan = self.s.plan_copy()
        T_cam_ct = None if self._last_trusted is None else self._last_trusted.T_cam_ct
        T_base_ct = None if (T_cam_ct is None or plan.T_base_cam is None) else plan.T_base_cam @ T_cam_ct
        q = T_tip = None
        tip_err = ang_err = None
        speed = 0.0
        lat = 1000 * self.latencies_s[-1] if self.latencies_s else None
        if self.robot is not None:
            st = self.robot.status()
            q, T_tip, speed = st.q, st.T_base_tip, st.speed_mm_s
            if T_tip is not None and T_base_ct is not None and plan.path_complete:
                from monotracker.robot.targets import tip_and_axis_error

                tip_err, ang_err = tip_and_axis_error(T_tip, T_base_ct, plan.entry_lps_mm, plan.target_lps_mm)
            robot = RobotSummary(st.state, frozen_array(q), tip_err, ang_err, float(speed), st.connected,
                                 st.message if st.program_fault else (self._holding_reason or st.message), lat,
                                 program_fault=st.program_fault, control=st.control)
        else:
            robot = RobotSummary("disarmed", None, None, None, 0.0, False, "robot not connected yet", None)
        scene = SceneGeometry(frozen_array(plan.T_base_cam), frozen_array(T_cam_ct), frozen_array(T_base_ct),
                              frozen_array(T_tip), frozen_array(self._target_T), frozen_array(q))
        return cam, pose, robot, scene
