"""A recording stand-in for ur_rtde's RTDEControlInterface / RTDEReceiveInterface (same method
names). One :class:`FakeUR` holds the joint state; ``speedJ`` sets the joint velocity and each
``getActualQ`` integrates it over one period. ``drop()`` kills the connection."""

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

    def drop(self):
        self.connected = False

    def control(self, host, freq):
        if not self.answer:
            raise RuntimeError("One of the RTDE input registers is already in use! / timeout")
        return FakeControl(self)

    def receive(self, host, freq):
        if not self.answer:
            raise RuntimeError("Connection refused")
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
        return True

    def kickWatchdog(self):
        self.ur.calls.append(("kickWatchdog",))
        return True

    def speedJ(self, qd, acceleration=0.5, time=0.0):
        if not self.ur.connected:
            raise RuntimeError("RTDE control interface is not connected")
        self.ur.calls.append(("speedJ", list(qd), acceleration, time))
        self.ur.dq = np.array(qd, dtype=float)
        return True

    def speedStop(self, a=10.0):
        self.ur.calls.append(("speedStop", a))
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
        return False
