"""Real UR arm through ur_rtde (``rtde_control.RTDEControlInterface``,
``rtde_receive.RTDEReceiveInterface``).

* Commands: ``speedJ(qd, acceleration, period)`` streamed once per control cycle, each followed
  by ``kickWatchdog()``. The RTDE watchdog (``setWatchdog(min_frequency)``) makes the robot
  program stop when Python stalls, because ur_rtde would otherwise keep repeating the last
  speed; our own stale-target timeout in the safety layer is the second line.
* Stops: ``speedStop(a)`` whenever the tracker stops (holding, armed, disarmed, e-stop);
  ``disconnect()`` also ends the script. Stop never raises.
* Connection loss: ``read``/``command_velocity`` raise :class:`ArmError` when either interface
  is down (the tracker then latches an e-stop). ``connect()`` after that tries ``reconnect()``
  on the existing interfaces first, then builds new ones. A robot in protective or emergency
  stop is reported as an ArmError too.

ur_rtde raises at once when no robot answers; the interface classes are injectable
(``control_factory``, ``receive_factory``) so tests run against a recording fake.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from monotracker.robot.arm import Arm, ArmError, ArmState

log = logging.getLogger(__name__)


def _default_control(host: str, frequency: float):
    import rtde_control

    return rtde_control.RTDEControlInterface(host, frequency)


def _default_receive(host: str, frequency: float):
    import rtde_receive

    return rtde_receive.RTDEReceiveInterface(host, frequency)


class URRTDEArm(Arm):
    def __init__(self, host: str, rate_hz: float = 125.0, watchdog_hz: float = 20.0,
                 control_factory=None, receive_factory=None, clock=time.monotonic):
        self.host = host
        self.rate_hz = float(rate_hz)
        self.period_s = 1.0 / self.rate_hz
        self.watchdog_hz = float(watchdog_hz)
        self._control_factory = control_factory or _default_control
        self._receive_factory = receive_factory or _default_receive
        self.clock = clock
        self.ctrl = None
        self.recv = None
        self._speed_mode = False

    # -------------------------------------------------------------- connection
    def connect(self) -> None:
        try:
            if self.ctrl is not None and self.recv is not None:
                ok_r = self.recv.isConnected() or self.recv.reconnect()
                ok_c = self.ctrl.isConnected() or self.ctrl.reconnect()
                if not (ok_r and ok_c):
                    raise ArmError(f"UR at {self.host}: reconnect failed")
            else:
                self.recv = self._receive_factory(self.host, self.rate_hz)
                self.ctrl = self._control_factory(self.host, self.rate_hz)
            if not self.ctrl.setWatchdog(self.watchdog_hz):
                raise ArmError(f"UR at {self.host}: could not enable the RTDE watchdog")
        except ArmError:
            raise
        except Exception as exc:  # noqa: BLE001 - ur_rtde raises RuntimeError for "no robot"
            raise ArmError(f"UR at {self.host} did not answer ({exc}); check the cable, IP and remote-control mode") from None
        self._speed_mode = False
        log.info("connected to UR at %s (%.0f Hz, watchdog %.0f Hz)", self.host, self.rate_hz, self.watchdog_hz)

    def disconnect(self) -> None:
        self.stop(4.0)
        for name, obj in (("control", self.ctrl), ("receive", self.recv)):
            if obj is None:
                continue
            try:
                if name == "control":
                    obj.stopScript()
                obj.disconnect()
            except Exception:  # noqa: BLE001
                log.exception("UR %s disconnect failed", name)

    def is_connected(self) -> bool:
        try:
            return bool(self.ctrl is not None and self.recv is not None
                        and self.ctrl.isConnected() and self.recv.isConnected())
        except Exception:  # noqa: BLE001
            return False

    # -------------------------------------------------------------- I/O
    def read(self) -> ArmState:
        if not self.is_connected():
            raise ArmError(f"UR at {self.host}: connection lost")
        try:
            if self.recv.isProtectiveStopped():
                raise ArmError("UR is in a protective stop: clear it on the teach pendant")
            if self.recv.isEmergencyStopped():
                raise ArmError("UR emergency stop is pressed")
            q = np.array(self.recv.getActualQ(), dtype=float)
            dq = np.array(self.recv.getActualQd(), dtype=float)
        except ArmError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise ArmError(f"UR at {self.host}: read failed ({exc})") from None
        if q.shape != (6,) or dq.shape != (6,):
            raise ArmError(f"UR at {self.host}: unexpected joint state size {q.shape}")
        return ArmState(q, dq, self.clock())

    def command_velocity(self, dq: np.ndarray, acceleration: float) -> None:
        dq = np.asarray(dq, dtype=float)
        if dq.shape != (6,) or not np.all(np.isfinite(dq)):
            raise ArmError("joint velocity command must be 6 finite numbers")
        if not self.is_connected():
            raise ArmError(f"UR at {self.host}: connection lost")
        try:
            ok = self.ctrl.speedJ(dq.tolist(), float(acceleration), self.period_s)
            self.ctrl.kickWatchdog()
        except Exception as exc:  # noqa: BLE001
            raise ArmError(f"UR at {self.host}: speedJ failed ({exc})") from None
        if ok is False:
            raise ArmError(f"UR at {self.host}: speedJ was refused")
        self._speed_mode = True

    def stop(self, deceleration: float) -> None:
        if self.ctrl is None:
            return
        try:
            if self._speed_mode:
                self.ctrl.speedStop(float(deceleration))
                self._speed_mode = False
            self.ctrl.kickWatchdog()
        except Exception:  # noqa: BLE001 - the robot's watchdog stops it if we cannot
            log.warning("UR stop command failed (connection down?); the RTDE watchdog will stop the arm")
