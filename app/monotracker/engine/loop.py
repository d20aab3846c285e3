"""The loop wiring: camera -> pose stream -> needle target -> tracker -> arm (being filled in)."""

from __future__ import annotations

import threading

from monotracker.engine.snapshot import CameraSummary, CommandResult, RobotSummary, SceneGeometry


class TrackingLoop:
    """Owns camera, pose stream, tracker and arm for a :class:`Session`."""

    def __init__(self, session):
        self.s = session
        self._lock = threading.RLock()

    def start_threads(self) -> None:
        pass

    def shutdown(self) -> None:
        pass

    def advance(self, dt: float) -> None:
        raise NotImplementedError("loop wiring lands with the vision and robot pieces")

    def robot_state(self) -> str:
        return "disarmed"

    def _na(self) -> CommandResult:
        return CommandResult(False, "camera/robot wiring not available yet in this build")

    set_camera = start_camera = stop_camera = arm = disarm = start_tracking = stop_tracking = \
        estop = reset_estop = inject_fault = lambda self, *a, **k: self._na()

    def latest_frame(self):
        return None

    def summaries(self):
        cam = CameraSummary(self.s.config.camera, False, 0.0, None, None, None, None, None)
        rob = RobotSummary("disarmed", None, None, None, 0.0, False, "not connected")
        return cam, None, rob, SceneGeometry(None, None, None, None, None, None)
