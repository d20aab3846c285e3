"""Real UR arm through ur_rtde (``rtde_control.RTDEControlInterface``,
``rtde_receive.RTDEReceiveInterface``).

* Commands: ``speedJ(qd, acceleration, period)`` streamed once per control cycle, each followed
  by ``kickWatchdog()``. The RTDE watchdog (``setWatchdog(min_frequency)``) makes the robot
  program stop when Python stalls, because ur_rtde would otherwise keep repeating the last
  speed; our own stale-target timeout in the safety layer is the second line.
* Stops (holding, armed, disarmed, e-stop): while the arm still moves, ``speedJ(0, a)`` is
  streamed (with the watchdog kick) each cycle, so it decelerates at ``a``; once it is at rest,
  ``speedStop(a)`` ends the speed mode. Not ``speedStop`` from speed: in ur_rtde it is not a
  streaming command, so it blocks the control thread until ``stopj`` has finished (up to
  ``v / a`` = 0.33 s at 1 rad/s and 3 rad/s^2) without updating the watchdog register, and a
  20 Hz watchdog then stops the robot program (every later command fails). ``disconnect()``
  uses a blocking ``speedStop`` (nothing follows) and ends the script. Stop never raises.
* Connection loss: ``read``/``command_velocity`` raise :class:`ArmError` when either interface
  is down (the tracker then latches an e-stop). ``connect()`` after that tries ``reconnect()``
  on the existing interfaces first, then builds new ones. A robot in protective or emergency
  stop is reported as an ArmError too.
* Link up, script stopped (``isProgramRunning()`` False: the RTDE watchdog fired, Stop on the
  pendant, a protective/emergency/safeguard stop, a script error): every command would return
  False and ``setWatchdog`` fails, so ``read`` raises :class:`ArmProgramStopped` with the cause
  (read from the receive interface: ``isProtectiveStopped``, ``isEmergencyStopped``,
  ``getSafetyMode``, ``getRuntimeState`` and how long ago we last kicked the watchdog).
  :meth:`recover` (the tracker calls it only from the operator's reset, in the e-stopped or
  disarmed state) re-uploads the script with ``reuploadScript()`` and re-enables the watchdog.
* Rate: ``rate_hz`` (125 for a CB3, 500 for an e-Series) is the RTDE frequency of both
  interfaces and the ``time`` argument of every ``speedJ``; the real-time thread is paced with
  ``initPeriod``/``waitPeriod`` (:meth:`begin_cycle`/:meth:`wait_cycle`).

ur_rtde raises at once when no robot answers; the interface classes are injectable
(``control_factory``, ``receive_factory``) so tests run against a recording fake.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from monotracker.robot.arm import Arm, ArmError, ArmProgramStopped, ArmState

log = logging.getLogger(__name__)


def _default_control(host: str, frequency: float):
    import rtde_control

    return rtde_control.RTDEControlInterface(host, frequency)


def _default_receive(host: str, frequency: float):
    import rtde_receive

    return rtde_receive.RTDEReceiveInterface(host, frequency)


#: UR safety modes (``getSafetyMode``) that stop the program, with a cause and an operator hint
_SAFETY_MODES = {
    3: ("protective_stop", "protective stop: clear it on the teach pendant, then reset"),
    5: ("safeguard_stop", "safeguard stop: clear the safeguard input, then reset"),
    6: ("emergency_stop", "system emergency stop: release it, then reset"),
    7: ("emergency_stop", "robot emergency stop: release it, then reset"),
    8: ("protective_stop", "safety violation: clear it on the teach pendant, then reset"),
    9: ("protective_stop", "safety fault: check the pendant, then reset"),
}
#: UR runtime state (``getRuntimeState``) 3 pausing, 4 paused
_PAUSED = (3, 4)


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
        #: clock time of the last successful watchdog kick (None: none yet)
        self._last_kick: float | None = None

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
            fault = self.program_fault()
            if fault is not None:  # setWatchdog would fail; reset restarts the script
                raise fault
            if not self.ctrl.setWatchdog(self.watchdog_hz):
                raise ArmError(f"UR at {self.host}: could not enable the RTDE watchdog")
        except ArmError:
            raise
        except Exception as exc:  # noqa: BLE001 - ur_rtde raises RuntimeError for "no robot"
            raise ArmError(f"UR at {self.host} did not answer ({exc}); check the cable, IP and remote-control mode") from None
        self._speed_mode = False
        self._last_kick = None
        log.info("connected to UR at %s (%.0f Hz, watchdog %.0f Hz)", self.host, self.rate_hz, self.watchdog_hz)

    def disconnect(self) -> None:
        if self.ctrl is not None and self._speed_mode:
            try:  # final stop: blocking is fine here, nothing else follows
                if self.ctrl.speedStop(4.0) is not False:
                    self._speed_mode = False
            except Exception:  # noqa: BLE001
                log.warning("UR stop command failed (connection down?); the RTDE watchdog will stop the arm")
        for name, obj in (("control", self.ctrl), ("receive", self.recv)):
            if obj is None:
                continue
            try:
                if name == "control":
                    obj.stopScript()
                obj.disconnect()
            except Exception:
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
            fault = self.program_fault()  # first: it names the cause (watchdog, pendant, ...)
            if fault is not None:
                raise fault
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
        # Marked before sending: once a speedJ may have reached the robot, every later stop
        # must send speedStop, even when this call raises half-way (speedJ sent, kick failed).
        self._speed_mode = True
        try:
            ok = self.ctrl.speedJ(dq.tolist(), float(acceleration), self.period_s)
            self.ctrl.kickWatchdog()
            self._last_kick = self.clock()
        except Exception as exc:  # noqa: BLE001
            raise ArmError(f"UR at {self.host}: speedJ failed ({exc})") from None
        if ok is False:
            raise ArmError(f"UR at {self.host}: speedJ was refused")

    #: joint speed (rad/s) below which the arm counts as at rest for ``speedStop``
    STANDSTILL_RAD_S = 1e-3

    def stop(self, deceleration: float) -> None:
        if self.ctrl is None:
            return
        try:
            if not self.ctrl.isProgramRunning():
                # the script is stopped: the robot has stopped the arm itself and refuses
                # every command; nothing to send until the operator's reset restarts it
                self._speed_mode = False
                return
        except Exception:  # noqa: BLE001 - unknown: try the stop below
            pass
        try:
            if self._speed_mode:
                try:
                    qd = np.abs(np.asarray(self.recv.getActualQd(), dtype=float))
                    # unknown (non-finite) speed: the plain, blocking stop, which surely stops
                    moving = bool(np.all(np.isfinite(qd)) and qd.max() > self.STANDSTILL_RAD_S)
                except Exception:  # noqa: BLE001 - unknown speed: the plain (blocking) stop
                    moving = False
                if moving:  # decelerate without blocking; the watchdog stays fed
                    ok = self.ctrl.speedJ([0.0] * 6, float(deceleration), self.period_s)
                else:  # at rest: returns at once
                    ok = self.ctrl.speedStop(float(deceleration))
                    if ok is not False:
                        self._speed_mode = False
                if ok is False:
                    log.warning("UR refused the stop command (program stopped?)")
            self.ctrl.kickWatchdog()
            self._last_kick = self.clock()
        except Exception:  # noqa: BLE001 - the robot's watchdog stops it if we cannot
            log.warning("UR stop command failed (connection down?); the RTDE watchdog will stop the arm")


    # -------------------------------------------------------------- script state / recovery
    def program_fault(self) -> ArmProgramStopped | None:
        """:class:`ArmProgramStopped` (cause + one-line reason) when the link is up but ur_rtde's
        control script is not running, else None. Never raises (unknown -> None; a dead link is
        :meth:`read`'s business)."""
        try:
            if self.ctrl is None or self.ctrl.isProgramRunning():
                return None
        except Exception:  # noqa: BLE001
            return None
        cause, why = "not_running", "stopped on the pendant or by a script error; reset restarts it"
        try:
            mode = int(self.recv.getSafetyMode()) if hasattr(self.recv, "getSafetyMode") else 1
        except Exception:  # noqa: BLE001
            mode = 1
        try:
            runtime = int(self.recv.getRuntimeState()) if hasattr(self.recv, "getRuntimeState") else -1
        except Exception:  # noqa: BLE001
            runtime = -1
        try:
            protective = bool(self.recv.isProtectiveStopped())
            emergency = bool(self.recv.isEmergencyStopped())
        except Exception:  # noqa: BLE001
            protective = emergency = False
        gap = None if self._last_kick is None else self.clock() - self._last_kick
        if emergency:
            cause, why = "emergency_stop", "emergency stop pressed: release it, then reset"
        elif protective:
            cause, why = _SAFETY_MODES[3]
        elif mode in _SAFETY_MODES:
            cause, why = _SAFETY_MODES[mode]
        elif gap is not None and self.watchdog_hz > 0 and gap > 1.0 / self.watchdog_hz:
            cause = "watchdog"
            why = (f"RTDE watchdog: no command for {gap * 1e3:.0f} ms (limit {1e3 / self.watchdog_hz:.0f} ms); "
                   "reset restarts the script")
        elif runtime in _PAUSED:
            cause, why = "paused", "program paused on the teach pendant; reset restarts the script"
        elif runtime in (0, 1):
            cause = "pendant"
        return ArmProgramStopped(f"UR control script not running ({why})", cause)

    def recover(self) -> None:
        """Re-upload ur_rtde's control script (``reuploadScript``) and re-enable the watchdog.
        Refused with a one-line :class:`ArmError` while the link is down or a protective/
        emergency stop is still active (the pendant must clear it first)."""
        if self.ctrl is None or not self.is_connected():
            raise ArmError(f"UR at {self.host}: not connected; reconnect first")
        fault = self.program_fault()
        if fault is None:
            return
        if fault.cause in ("protective_stop", "emergency_stop", "safeguard_stop"):
            raise ArmError(f"cannot restart the UR control script: {fault}")
        try:
            ok = self.ctrl.reuploadScript()
            running = bool(self.ctrl.isProgramRunning())
        except Exception as exc:  # noqa: BLE001
            raise ArmError(f"UR at {self.host}: script re-upload failed ({exc})") from None
        if ok is False or not running:
            raise ArmError(f"UR at {self.host}: the control script did not start again; "
                           "check remote-control mode on the pendant")
        try:
            wd = self.ctrl.setWatchdog(self.watchdog_hz)
        except Exception as exc:  # noqa: BLE001
            raise ArmError(f"UR at {self.host}: could not enable the RTDE watchdog ({exc})") from None
        if not wd:
            raise ArmError(f"UR at {self.host}: could not enable the RTDE watchdog")
        self._speed_mode = False
        self._last_kick = None
        log.info("UR control script re-uploaded after: %s", fault)

    # -------------------------------------------------------------- pacing
    def begin_cycle(self):
        if self.ctrl is None or not hasattr(self.ctrl, "initPeriod"):
            return None
        try:
            return self.ctrl.initPeriod()
        except Exception:  # noqa: BLE001 - fall back to the tracker's own sleep
            return None

    def wait_cycle(self, token) -> bool:
        if token is None or self.ctrl is None:
            return False
        try:
            self.ctrl.waitPeriod(token)
            return True
        except Exception:  # noqa: BLE001
            return False


def read_joint_state(host: str, rate_hz: float = 125.0, receive_factory=None, clock=time.monotonic) -> ArmState:
    """Read a UR's joint state through the RTDE *receive* interface only (rad, rad/s).

    Never opens the control interface: constructing one uploads ur_rtde's control script,
    which stops whatever program the robot runs. Raises :class:`ArmError` (one line)."""
    factory = receive_factory or _default_receive
    recv = None
    try:
        recv = factory(host, float(rate_hz))
        q = np.array(recv.getActualQ(), dtype=float)
        dq = np.array(recv.getActualQd(), dtype=float)
    except Exception as exc:  # noqa: BLE001 - ur_rtde raises RuntimeError for "no robot"
        raise ArmError(f"UR at {host} did not answer ({exc}); check the cable and IP") from None
    finally:
        if recv is not None:
            try:
                recv.disconnect()
            except Exception:
                log.exception("UR receive disconnect failed")
    if q.shape != (6,) or dq.shape != (6,) or not (np.all(np.isfinite(q)) and np.all(np.isfinite(dq))):
        raise ArmError(f"UR at {host}: unexpected joint state {q}")
    return ArmState(q, dq, clock())
