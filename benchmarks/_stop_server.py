"""The app under test for ``benchmarks/stop_latency.py``: one real-clock session (the rendered
twin camera at 30 fps, detection, registration, a breathing head, the simulated UR10 in its
control process, tracking) served by the web app, driven through stdin/stdout JSON lines.

Run with ``PYTHONPATH=<tree>/app`` so the same script drives today's code (a worktree of the
commit before the change) and ours; it uses only what both have: the ``Session`` API, the web
app, the control process's ``state()`` and ``on_event``. The priority policy in force is the
tree's own (nothing here changes a priority).

Commands (one JSON object per line in, one per line out):

* ``{"cmd": "prepare"}``: the local operator (the Session API, not the page) resets the e-stop,
  arms and starts tracking; answers once the arm tracks or holds (or, tracking refused for
  15 s for want of a fresh pose, is armed).
* ``{"cmd": "arm_measure"}``: forget the last stop's times and watch for the next one: the
  control process's own transition to ``estopped`` (its clock, reported with the transition:
  the stop latched and the arm commanded to stop) and the first published state with the arm
  standing still (a sampler reads the control process's shared state every 2 ms; each state
  carries the control cycle's own time).
* ``{"cmd": "result", "wait_s": S}``: those times (wall-clock s, ``time.time()`` base) once
  both are known (or what is known after S).
* ``{"cmd": "api_press"}``: the no-browser case: ``Session.estop()`` called from a new thread as
  the web server's handler would; answers the call's own duration and the time until
  ``Session.snapshot()`` (read in a loop by a third thread) says ``estopped`` (ms).
* ``{"cmd": "quit"}``.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

STILL_RAD_S = 1e-3  # every joint slower than this: the arm stands still
WALL = time.time() - time.monotonic()  # monotonic (system-wide) -> wall clock


#: protocol lines start with this (anything else on stdout, viser's banner say, is not ours)
TAG = "@@stop-bench "


def say(obj) -> None:
    sys.stdout.write(TAG + json.dumps(obj) + "\n")
    sys.stdout.flush()


class Probe:
    """The control process's own report of a stop (the transition event's time) and the first
    published state with the arm still, after :meth:`arm`."""

    def __init__(self, session):
        self.s = session
        self.lock = threading.Lock()
        self.armed = False
        self.ack_t = None
        self.still_t = None
        self.recv_t = None  # the web server's STOP handler called Session.request_estop
        self.sock_t = None  # the last message viser read off a websocket before that call
        self.signal_t = None  # the engine wrote the stop into the control process's stop slot
        self._last_msg_t = None
        self.speed = None  # the arm's fastest joint (rad/s) in the last state before the stop
        self.proc = None
        self._hooked = None
        self._sampler = None

    def hook(self):
        self._hook_request()
        # the loop's robot part (engine/loop/robot.RobotControl) holds the rig; the rig of a
        # control process holds it as ``proc`` (engine/rigs/robot_process.py)
        rob = self.s._loop.robot
        rig = getattr(rob, "rig", None) or rob
        proc = getattr(rig, "proc", None)
        if proc is None:
            print("stop-bench: no control process found on the session's robot: ack / still are not measured",
                  file=sys.stderr, flush=True)
            return
        if proc is self._hooked:
            return
        orig = proc.on_event

        def on_event(kind, payload):
            if kind == "transition" and payload.get("to") == "estopped":
                with self.lock:
                    if self.armed and self.ack_t is None:
                        self.ack_t = float(payload["t"]) + WALL
                        # when the engine signalled it: the stop slot's [request, monotonic time]
                        slot = getattr(proc, "stop_slot", None)
                        got = slot.read() if slot is not None else None
                        self.signal_t = float(got[1][1]) + WALL if got is not None else None
            if orig is not None:
                orig(kind, payload)

        proc.on_event = on_event
        self.proc = self._hooked = proc

    def _hook_request(self):
        """Stamp the moment the web server's STOP handler enters ``Session.request_estop`` (both
        trees have it; the handler looks it up on the session at each press), to split a press's
        latency into browser -> server handler (``recv``) and handler -> the control process's
        latch (``latch``)."""
        orig = getattr(self.s, "request_estop", None)
        if orig is None or getattr(orig, "_stop_probe", False):
            return

        def request_estop(*a, **k):
            with self.lock:
                if self.armed and self.recv_t is None:
                    self.recv_t = time.time()
                    self.sock_t = self._last_msg_t
            return orig(*a, **k)

        # viser's websocket consumer decodes each incoming message (Message.deserialize) on its
        # event loop as it reads it; the STOP handler runs as a task after that: the last decode
        # before the handler is the STOP's (measurement only; absent in a viser without it)
        try:
            from viser.infra._messages import Message
        except ImportError:
            Message = None
        des = getattr(Message, "deserialize", None)
        if des is not None and not getattr(des, "_stop_probe", False):
            fn = des.__func__

            def deserialize(cls, raw):
                self._last_msg_t = time.time()
                return fn(cls, raw)

            deserialize._stop_probe = True
            Message.deserialize = classmethod(deserialize)

        request_estop._stop_probe = True
        self.s.request_estop = request_estop

    def arm(self):
        self.hook()
        with self.lock:
            self.armed, self.ack_t, self.still_t, self.speed = True, None, None, None
            self.recv_t, self.sock_t, self.signal_t = None, None, None
        self._sampler = threading.Thread(target=self._sample, daemon=True)
        self._sampler.start()

    def _sample(self):
        t_end = time.monotonic() + 120.0
        while time.monotonic() < t_end:
            st = self.proc.state() if self.proc is not None else None
            dq = None if st is None else (st.true_dq if np.all(np.isfinite(st.true_dq)) else st.dq)
            if st is not None and st.state != "estopped" and np.all(np.isfinite(dq)):
                self.speed = float(np.max(np.abs(dq)))
            if st is not None and st.state == "estopped":
                if np.all(np.isfinite(dq)) and float(np.max(np.abs(dq))) < STILL_RAD_S:
                    with self.lock:
                        if self.still_t is None:
                            self.still_t = float(st.t) + WALL
                    return
            time.sleep(0.002)

    def result(self, timeout_s: float) -> dict:
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            with self.lock:
                if self.ack_t is not None and self.still_t is not None:
                    break
            time.sleep(0.01)
        with self.lock:
            self.armed = False
            still = self.still_t
            if still is not None and self.ack_t is not None:
                still = max(still, self.ack_t)  # the arm already stood still when the stop latched
            return {"ack_t": self.ack_t, "still_t": still, "speed_rad_s": self.speed, "recv_t": self.recv_t,
                    "sock_t": self.sock_t, "signal_t": self.signal_t}


def wait(pred, timeout_s: float, poll_s: float = 0.02):
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        v = pred()
        if v:
            return v
        time.sleep(poll_s)
    return None


def prepare(s, pin: str, timeout_s: float = 60.0, track_wait_s: float = 15.0) -> dict:
    """Reset, arm and start tracking (the local operator), retried while the pose is not fresh.

    Ready when the arm tracks or holds (tracking, with a late pose); when tracking is refused
    for ``track_wait_s`` (no fresh trusted pose: on a loaded machine the camera may not keep up)
    an armed arm is ready too: STOP is then pressed on an armed arm with the camera running,
    and the press's row says from which state."""
    t0 = time.monotonic()
    t_end = t0 + timeout_s
    last = ""
    while time.monotonic() < t_end:
        state = s.snapshot().robot.state
        if state in ("tracking", "holding"):
            return {"ok": True, "state": state}
        if state == "armed" and time.monotonic() - t0 > track_wait_s:
            return {"ok": True, "state": state, "last": last}
        if state == "estopped":
            last = s.reset_estop().message
        elif state == "disarmed":
            last = s.arm(pin).message
        elif state in ("armed", "holding"):
            last = s.start_tracking().message
        time.sleep(0.05)
    return {"ok": False, "state": s.snapshot().robot.state, "last": last}


def api_press(s) -> dict:
    """Session.estop() from another thread (as a web handler); the snapshot read by a third."""
    out = {}
    t0 = time.monotonic()

    def call():
        s.estop()
        out["call_ms"] = 1000 * (time.monotonic() - t0)

    def poll():
        while time.monotonic() - t0 < 60.0:
            if s.snapshot().robot.state == "estopped":
                out["snapshot_ms"] = 1000 * (time.monotonic() - t0)
                return
            time.sleep(0.001)

    th = [threading.Thread(target=call), threading.Thread(target=poll)]
    for t in th:
        t.start()
    for t in th:
        t.join(90.0)
    return out


def plan_in(home: Path) -> None:
    """The phantom's fiducials confirmed and the sample path planned in ``home`` (a
    simulated-clock session of the tree under test makes it)."""
    from monotracker.engine import Session, SessionConfig
    from monotracker.sim.phantom import default_phantom

    s = Session(SessionConfig(home=home, clock="sim"))
    try:
        ph = default_phantom()
        for c in ph.fiducial_centres_lps:
            assert s.add_fiducial(c, ph.fiducial_radius_mm).ok
        assert s.confirm_fiducials().ok
        assert s.use_sample_plan().ok
    finally:
        s.shutdown()


def main() -> int:
    home, port, pin = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
    from monotracker.engine import Session, SessionConfig
    from monotracker.ui.app import MonoTrackerApp

    plan_in(home)
    s = Session(SessionConfig(home=home, camera="sim", trajectory="breathing", robot="sim", arm_pin=pin, clock="real"))
    s.start()
    app = MonoTrackerApp(s, "127.0.0.1", port)
    app.start()
    probe = Probe(s)
    try:
        if not s.start_camera().ok:
            say({"ok": False, "error": "camera did not start"})
            return 1
        ok = wait(lambda: s.snapshot().pose is not None and s.snapshot().pose.trusted, 180.0)
        say({"ok": bool(ok), "url": app.url, "control": str(getattr(s._loop.robot, "control", ""))})
        for line in sys.stdin:
            msg = json.loads(line)
            cmd = msg.get("cmd")
            if cmd == "prepare":
                r = prepare(s, pin)
                probe.hook()
                say(r)
            elif cmd == "arm_measure":
                probe.arm()
                say({"ok": True})
            elif cmd == "result":
                say(probe.result(float(msg.get("wait_s", 30.0))))
            elif cmd == "api_press":
                say(api_press(s))
            elif cmd == "quit":
                say({"ok": True})
                break
            else:
                say({"ok": False, "error": f"unknown command {cmd!r}"})
    finally:
        app.stop()
        s.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
