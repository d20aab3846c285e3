"""The tracking loop: camera -> pose -> trust verdict -> needle target -> tracker -> arm.

* ``core.py`` -- :class:`TrackingLoop`: the pose side (verdict, holds and resumes, the target,
  listeners), composing its parts;
* ``gate.py`` -- :class:`PoseGate`, the per-frame trust verdict built from ``SessionConfig``;
* ``camera.py`` / ``robot.py`` -- the camera and robot controls (their rigs, commands, watchdogs);
* ``clocks.py`` -- what drives it: the simulated clock (:class:`SimStepper`, :class:`SimClock`) or
  the engine thread (:class:`RealThread`);
* ``summaries.py`` -- the read side for the snapshot.
"""

from monotracker.engine.loop.clocks import RealThread, SimClock, SimStepper
from monotracker.engine.loop.core import PoseRecord, TrackingLoop
from monotracker.engine.loop.gate import GateVerdict, PoseGate

__all__ = ["GateVerdict", "PoseGate", "PoseRecord", "RealThread", "SimClock", "SimStepper", "TrackingLoop"]
