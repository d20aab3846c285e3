"""Stick-and-ball drawing of the UR10 from its URDF (example-robot-data) with pinocchio.

``joint_chain_mm(q)`` returns the base origin, every joint origin and the tool flange (tool0)
in the robot base frame, millimetres, for joint angles ``q`` (6,) rad. The web app draws thick
segments between consecutive points and spheres at the joints: enough to see the arm's pose
follow the state without shipping mesh files.
"""

from __future__ import annotations

import functools
import threading

import numpy as np

_lock = threading.Lock()


@functools.lru_cache(maxsize=1)
def _model():
    import pinocchio as pin

    from monotracker.robot.kinematics import urdf_path

    model = pin.buildModelFromUrdf(str(urdf_path()))
    tool = model.getFrameId("tool0")
    return pin, model, model.createData(), tool


def joint_chain_mm(q) -> np.ndarray:
    """(8, 3) points, base frame mm: base, the six joint origins, tool0."""
    pin, model, data, tool = _model()
    q = np.asarray(q, float).reshape(model.nq)
    with _lock:  # one shared data buffer
        pin.forwardKinematics(model, data, q)
        pin.updateFramePlacements(model, data)
        pts = [np.zeros(3)] + [np.array(data.oMi[j].translation) for j in range(1, model.njoints)]
        pts.append(np.array(data.oMf[tool].translation))
    return np.array(pts) * 1000.0
