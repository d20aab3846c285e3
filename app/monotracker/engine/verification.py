"""Accuracy verification before the robot moves: validation fiducials, the arming gate, the report.

The plan can give fiducials the role ``"validation"`` (``Session.set_fiducial_role``): they stay out
of the fit, and every estimate measures the error at each of them (``registration.validation``:
point-to-viewing-ray distance, mm, the same measure as the FRE). The camera rigs compute it per
frame (:class:`~monotracker.engine.rigs.validation.ValidationSet`), it is shown in ``snap.pose.validation_tre_mm`` beside the FRE and
the predicted TRE, and arming is refused (:func:`arm_refusal`) unless the newest pose is trusted,
fresh, and every validation fiducial is seen and within ``SessionConfig.max_validation_tre_mm``.
Each arming attempt writes ``verification.json`` in the session folder (:func:`write_report`).

Why 1.5 mm by default: the paper's validation-fiducial TRE is 0.58 mm mean, 0.90 mm max over six
experiments, and the twin measures ~0.3 mm; 1.5 mm leaves room for a real camera's noise while
catching a fiducial that moved on the scalp or a wrong registration well before the error reaches
the 2-3 mm at which a puncture path is clinically off (and matches the engine's FRE gate).
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import numpy as np

VERIFICATION_FILE = "verification.json"


def arm_refusal(session) -> str | None:
    """Why arming must be refused on accuracy grounds (one line), or None. Without validation
    fiducials there is nothing to verify (the report says so)."""
    plan = session.plan_copy()
    if not plan.validation_fiducials():
        return None
    rec = session.latest_pose()
    cfg = session.config
    if rec is None:
        return "no pose yet: the registration cannot be verified"
    if not rec.trusted or rec.sample.T_cam_ct is None:
        return f"no trusted pose ({rec.reason}): the registration cannot be verified"
    if float(session.clock()) - rec.sample.t_capture > cfg.max_pose_age_s:
        return "the newest pose is stale: the registration cannot be verified"
    v = rec.sample.validation
    if v is None:
        return "no validation measurement for the newest pose"
    return None if v.ok else v.reason


def report(session, decision: str, refusal: str | None) -> dict:
    """The verification report (JSON-ready): pose quality and validation errors at this moment."""
    rec = session.latest_pose()
    plan = session.plan_copy()
    smp = None if rec is None else rec.sample
    v = None if smp is None else smp.validation
    return {
        "format": "monotracker-verification", "version": 1,
        "time_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds"),
        "session_id": session.session_id, "plan_revision": plan.revision, "decision": decision,
        "refusal": refusal, "limit_mm": session.config.max_validation_tre_mm,
        "measure": "distance (mm) of each validation fiducial, mapped by T_cam_ct, to the viewing ray through "
                   "its detected image centre (sphere-bias corrected); lower bound of the 3D error there",
        "registration_fiducials": [f.id for f in plan.registration_fiducials()],
        "validation_fiducials": [f.id for f in plan.validation_fiducials()],
        "pose": None if smp is None else {
            "t_capture": smp.t_capture, "frame": smp.frame_index, "trusted": bool(rec.trusted),
            "reason": rec.reason, "n_matched": smp.n_matched, "fre_mm": smp.fre_mm,
            "predicted_tre_mm": smp.predicted_tre_mm,
            "T_cam_ct_mm": None if smp.T_cam_ct is None else np.asarray(smp.T_cam_ct).tolist()},
        "validation": None if v is None else v.to_dict(),
    }


def write_report(session, decision: str, refusal: str | None) -> Path:
    from monotracker.engine.persistence import atomic_write_json

    path = Path(session.home) / VERIFICATION_FILE
    atomic_write_json(path, report(session, decision, refusal))
    return path
