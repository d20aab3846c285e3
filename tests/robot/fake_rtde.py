"""A recording stand-in for ur_rtde's RTDEControlInterface / RTDEReceiveInterface (same method
names). One :class:`FakeUR` holds the joint state; ``speedJ`` sets the joint velocity and each
``getActualQ`` integrates it over one period. ``drop()`` kills the connection.

Modelled from ur_rtde 1.6's source: ``speedStop`` is *not* one of the streaming commands, so
``sendCommand`` blocks until the script's ``stopj`` has brought the arm to rest (``max|qd| / a``
seconds) without writing the watchdog register meanwhile; the script's
``rtde_set_watchdog(..., "stop")`` then stops the program if that exceeds ``1 / min_frequency``,
after which every command is refused (returns False). ``blocked_s`` records each blocking time.

Script stopped with the link up (ur_rtde 1.6 behaviour as described in its docs and issue 15):
``stop_script(cause)`` stops the program as the RTDE watchdog (``"watchdog"``), Stop on the pendant
(``"pendant"``), Pause (``"paused"``) or a protective stop (``"protective_stop"``) would; then
``isProgramRunning()`` is False, every command returns False, ``isConnected()`` stays True,
``setWatchdog`` returns False (the "could not enable the RTDE watchdog" trap), and only
``reuploadScript()`` brings the program back (refused while a protective stop is active).
The receive side reports ``getSafetyMode`` (1 normal, 3 protective stop) and ``getRuntimeState``
(1 stopped, 2 playing, 4 paused). ``initPeriod``/``waitPeriod`` are recorded (no sleeping)."""

import numpy as np


class FakeUR:
    def __init__(self, q0, period=1 / 125.0, answer=True):
        self.q = np.array(q0, dtype=float)
        self.dq = np.zeros(6)
        self.period = period
        self.connected = answer
        self.answer = answer
        self.calls = []
        self.can_reconnect = True
        self.protective_stop = False
        #: kickWatchdog raises (the link died between speedJ and the kick)
        self.fail_kick = False
        self.watchdog_hz = None
        self.program_running = True
        self.blocked_s = []
        self.runtime_state = 2  # playing
        self.emergency_stop = False
        self.freq = {}

    def stop_script(self, cause="pendant"):
        """The control script stops; the link stays up."""
        self.program_running = False
        self.dq = np.zeros(6)  # the robot brings itself to rest
        self.runtime_state = 4 if cause == "paused" else 1
        if cause == "protective_stop":
            self.protective_stop = True

    def drop(self):
        self.connected = False

    def control(self, host, freq):
        if not self.answer:
            raise RuntimeError("One of the RTDE input registers is already in use! / timeout")
        self.freq["control"] = freq
        self.program_running = True  # the constructor uploads the script
        self.runtime_state = 2
        return FakeControl(self)

    def receive(self, host, freq):
        if not self.answer:
            raise RuntimeError("Connection refused")
        self.freq["receive"] = freq
        return FakeReceive(self)

    def names(self):
        return [c[0] for c in self.calls]


class _Base:
    def __init__(self, ur):
        self.ur = ur

    def isConnected(self):
        return self.ur.connected

    def reconnect(self):
        self.ur.calls.append(("reconnect",))
        if self.ur.can_reconnect:
            self.ur.connected = True
        return self.ur.connected

    def disconnect(self):
        self.ur.calls.append(("disconnect",))


class FakeControl(_Base):
    def setWatchdog(self, min_frequency=10.0):
        self.ur.calls.append(("setWatchdog", min_frequency))
        if not self.ur.program_running:
            return False
        self.ur.watchdog_hz = min_frequency
        return True

    def isProgramRunning(self):
        return self.ur.program_running

    def reuploadScript(self):
        self.ur.calls.append(("reuploadScript",))
        if not self.ur.connected or self.ur.protective_stop or self.ur.emergency_stop:
            return False
        self.ur.program_running = True
        self.ur.runtime_state = 2
        return True

    def initPeriod(self):
        self.ur.calls.append(("initPeriod",))
        return len(self.ur.calls)

    def waitPeriod(self, t_start):
        self.ur.calls.append(("waitPeriod", t_start))

    def kickWatchdog(self):
        if self.ur.fail_kick:
            self.ur.fail_kick = False
            raise RuntimeError("RTDE control interface: send failed")
        self.ur.calls.append(("kickWatchdog",))
        return True

    def speedJ(self, qd, acceleration=0.5, time=0.0):
        if not self.ur.connected:
            raise RuntimeError("RTDE control interface is not connected")
        self.ur.calls.append(("speedJ", list(qd), acceleration, time))
        if not self.ur.program_running:
            return False
        self.ur.dq = np.array(qd, dtype=float)
        return True

    def speedStop(self, a=10.0):
        self.ur.calls.append(("speedStop", a))
        if not self.ur.program_running:
            return False
        blocked = float(np.abs(self.ur.dq).max()) / a
        self.ur.blocked_s.append(blocked)
        if self.ur.watchdog_hz and blocked > 1.0 / self.ur.watchdog_hz:
            self.ur.program_running = False  # watchdog: no register update while blocked
        self.ur.dq = np.zeros(6)
        return True

    def servoStop(self, a=10.0):
        self.ur.calls.append(("servoStop", a))
        return True

    def stopScript(self):
        self.ur.calls.append(("stopScript",))


class FakeReceive(_Base):
    def getActualQ(self):
        self.ur.q = self.ur.q + self.ur.dq * self.ur.period
        return list(self.ur.q)

    def getActualQd(self):
        return list(self.ur.dq)

    def isProtectiveStopped(self):
        return self.ur.protective_stop

    def isEmergencyStopped(self):
        return self.ur.emergency_stop

    def getSafetyMode(self):
        return 7 if self.ur.emergency_stop else (3 if self.ur.protective_stop else 1)

    def getRuntimeState(self):
        return self.ur.runtime_state
