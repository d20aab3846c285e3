"""OpenIGTLink server: the live session to 3D Slicer (OpenIGTLinkIF) or any OpenIGTLink client.

``IGTLStreamer(session, port, allow_remote=False).start()`` serves OpenIGTLink (``pyigtl``) on
127.0.0.1 (every interface only with ``allow_remote``, as for the web app) and sends, for every
camera estimate the engine handles (the pose rate: one ``CTToCamera`` per trusted pose, none
dropped on the way while clients read; issue 29):

=================  =========  =================================================================
device name        type       content
=================  =========  =================================================================
``CTToCamera``     TRANSFORM  ``T_cam_ct``: CT (RAS, mm) -> camera (OpenCV frame, mm)
``NeedleTipToCT``  TRANSFORM  needle tip frame (z along the needle) -> CT (RAS, mm), from the
                              robot's measured tip pose and the current registration
``Status``         STRING     ``key=value; ...``: robot state, pose validity and reason, pose age
                              (ms), fiducials matched, FRE (mm), validation-fiducial verdict,
                              recent alert codes, coordinates
``Fiducials``      POINT      the registration fiducials (CT RAS mm, named ``F<id>``)
``Path``           POINT      ``Entry`` and ``Target`` (CT RAS mm)
=================  =========  =================================================================

Coordinates: MonoTracker works in LPS (DICOM); 3D Slicer's world is RAS. Everything CT-side is sent
in RAS (``F = diag(-1, -1, 1)``: ``CTToCamera = T_cam_ct @ F``, ``NeedleTipToCT = F @ T_ct_tip``,
points ``F @ p``) so that a CT loaded into Slicer lines up with no extra transform;
``coordinates="LPS"`` sends MonoTracker's own frame instead. The ``Status`` string names it.

Only valid data is sent: ``CTToCamera`` and ``NeedleTipToCT`` go out for every pose the engine
trusts (``trusted``: >= min fiducials, FRE gate, jump gate, predicted error), each stamped with
its frame's capture time, and for no other (a Slicer transform node keeps its last value, so the
``Status`` message says ``pose=INVALID`` with the reason and ``last_valid_age_ms``, every frame).
A trusted pose that reached the engine later than ``max_pose_age_s`` after capture (the arm holds
for it) is still sent, under its own capture time, and ``Status`` says ``late=yes``: the pose is
right for the moment it was captured, and a client that reads the timestamps knows its age
(withholding it cut the stream to 11 Hz on a busy machine while the tracker ran at 16-18 Hz).
``NeedleTipToCT`` goes out only with a fresh pose: it joins the arm's tip as it is now to the
frame's pose, and for a late pose the head may have moved in between.
Each message's OpenIGTLink timestamp is the frame's capture time on the wall clock
(``epoch0 + t_capture``, where ``epoch0`` maps the session clock to Unix time when streaming
starts; with the simulated clock this is simulated time, so rates read from the timestamps are the
camera's rate, not the speed of the machine). Fiducials and path are sent on every new connection,
when the plan changes and every 2 s of session time.

Clients (``interop/igtl_server.py``): several at a time (at most 8), each with its own bounded
queue: a client receives only what was sent after it connected; one that stops reading for 2 s
is dropped, one that declares a message body over 64 KiB is disconnected (the server reads
nothing it needs from clients), and neither slows the engine or the other clients. The engine
thread only copies a few matrices into a short queue; a streamer thread builds the messages and
the server's own thread sends them. Connections, departures and drops are audit rows. OpenIGTLink
has no authentication: anyone who reaches the port receives the stream, which is why it is served
on 127.0.0.1 unless every interface is asked for explicitly.
"""

from __future__ import annotations

import collections
import logging
import threading
import time

import numpy as np

from monotracker.errors import InputError

log = logging.getLogger(__name__)

DEFAULT_PORT = 18944
F_LPS_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
DEVICES = ("CTToCamera", "NeedleTipToCT", "Status", "Fiducials", "Path")
STATIC_EVERY_S = 2.0
#: poses waiting for the streamer thread (the engine thread only appends): ~8 s at 30 Hz, so a
#: busy moment never drops one; beyond it the oldest go first and are counted (``dropped``)
POSE_QUEUE = 256


def _make_server(port: int, allow_remote: bool, on_event=None):
    """The OpenIGTLink server (:class:`~monotracker.interop.igtl_server.IGTLServer`) bound to
    127.0.0.1, or to every interface with ``allow_remote``; started. OpenIGTLink has no
    authentication: every client that reaches the port receives the stream."""
    from monotracker.interop.igtl_server import IGTLServer

    host = "0.0.0.0" if allow_remote else "127.0.0.1"
    return IGTLServer(host, int(port), on_event=on_event).start()


class IGTLStreamer:
    """See the module docstring. ``sent`` counts messages sent per device name; ``dropped`` the
    poses lost before they were sent (a full queue)."""

    def __init__(self, session, port: int = DEFAULT_PORT, allow_remote: bool = False, coordinates: str = "RAS"):
        if not (0 < int(port) < 65536):
            raise InputError(f"--igtl-port must be between 1 and 65535, not {port}")
        if coordinates not in ("RAS", "LPS"):
            raise InputError("coordinates must be RAS or LPS")
        self.s = session
        self.port = int(port)
        self.allow_remote = bool(allow_remote)
        self.coordinates = coordinates
        self.F = F_LPS_RAS if coordinates == "RAS" else np.eye(4)
        self.sent = collections.Counter()
        self._q: collections.deque = collections.deque(maxlen=POSE_QUEUE)  # the oldest go first when full
        self.dropped = 0  # poses dropped from a full queue (the streamer thread starved)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._server = None
        self._thread: threading.Thread | None = None
        self._remove_hook = None
        self._static_sent_at = None
        self._static_revision = None
        self._last_valid_t = None
        self.epoch0 = None

    @property
    def host(self) -> str | None:
        return None if self._server is None else self._server.host

    def start(self) -> "IGTLStreamer":
        self._server = _make_server(self.port, self.allow_remote, self._on_server_event)
        self._server.on_connect = self._on_connect
        self.epoch0 = time.time() - float(self.s.clock())
        self._remove_hook = self.s.add_pose_listener(self._on_pose)
        self._thread = threading.Thread(target=self._run, name="monotracker-igtl", daemon=True)
        self._thread.start()
        self.s.record("igtl_started", f"OpenIGTLink server on {self._server.host}:{self.port} ({self.coordinates})",
                      {"host": self._server.host, "port": self.port, "coordinates": self.coordinates})
        return self

    def stop(self) -> None:
        if self._remove_hook is not None:
            self._remove_hook()
            self._remove_hook = None
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        if self._server is not None:
            try:
                self._server.stop()
            except Exception:  # closing must not raise at shutdown
                log.exception("stopping the OpenIGTLink server failed")
            self._server = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    def _on_server_event(self, code: str, message: str, data: dict) -> None:
        """Connections, departures and dropped clients, to the audit log (who received the stream)."""
        level = data.pop("level", "info") if code != "igtl_client_refused" else "warning"
        try:
            self.s.record(code, message, data, level=level)
        except Exception:  # the stream must never take the engine down
            log.exception("OpenIGTLink event not recorded")

    def _on_connect(self) -> None:
        self._static_sent_at = None  # fiducials and path go to the new client with the next frame
        self._wake.set()

    # ------------------------------------------------------------------ engine thread
    def _on_pose(self, smp, trusted: bool, now: float) -> None:
        srv = self._server
        if srv is None or not srv.is_connected():
            return
        s = self.s
        st = s.robot_status()
        alerts = [e.code for e in s.recent_alerts(3)]
        rec = s.latest_pose()
        if len(self._q) == self._q.maxlen:
            self.dropped += 1
        self._q.append({
            "t_capture": float(smp.t_capture), "now": float(now), "trusted": bool(trusted),
            "fresh": now - smp.t_capture <= s.config.max_pose_age_s,
            "reason": (rec.reason if rec is not None and not trusted else smp.reason) or "",
            "T_cam_ct": None if smp.T_cam_ct is None else np.array(smp.T_cam_ct, float),
            "n": int(smp.n_matched), "fre": smp.fre_mm,
            "robot": "none" if st is None else st.state,
            "T_base_tip": None if st is None or st.T_base_tip is None else np.array(st.T_base_tip, float),
            "alerts": alerts,
            "validation": ("none" if smp.validation is None else
                           (f"ok max_mm={smp.validation.max_mm:.2f}" if smp.validation.ok else "FAILED")),
        })
        self._wake.set()

    # ------------------------------------------------------------------ streamer thread
    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.2)
            self._wake.clear()
            try:
                self._service()
            except Exception:  # the stream must never take the engine down
                log.exception("OpenIGTLink streaming failed")

    def _service(self) -> None:
        srv = self._server
        if srv is None:
            return
        if not srv.is_connected():
            self._q.clear()
            return
        while self._q:
            self._send_frame(self._q.popleft())

    def _send(self, msg) -> None:
        self._server.broadcast(msg.pack())
        self.sent[msg.device_name] += 1

    def _send_frame(self, d: dict) -> None:
        import pyigtl

        ts = self.epoch0 + d["t_capture"]
        plan = self.s.plan_copy()
        valid = d["trusted"] and d["T_cam_ct"] is not None
        tip_sent = False
        if valid:
            self._last_valid_t = d["t_capture"]
            T_cam_ct = d["T_cam_ct"]
            self._send(pyigtl.TransformMessage(T_cam_ct @ self.F, timestamp=ts, device_name="CTToCamera"))
            # the tip is the arm's now and the pose the frame's: for a late pose the head may have
            # moved in between, so the tip in the CT is sent only with a fresh pose
            if d["T_base_tip"] is not None and plan.T_base_cam is not None and d["fresh"]:
                T_ct_tip = np.linalg.inv(plan.T_base_cam @ T_cam_ct) @ d["T_base_tip"]
                self._send(pyigtl.TransformMessage(self.F @ T_ct_tip, timestamp=ts, device_name="NeedleTipToCT"))
                tip_sent = True
        if valid:
            pose = "pose=VALID; late=" + ("no" if d["fresh"] else "yes")
        else:
            why = d["reason"] or "no pose"
            last = "none" if self._last_valid_t is None else f"{1000 * (d['now'] - self._last_valid_t):.0f}"
            pose = f"pose=INVALID; reason={why}; last_valid_age_ms={last}"
        fre = "n/a" if d["fre"] is None else f"{d['fre']:.3f}"
        status = (f"robot={d['robot']}; {pose}; age_ms={1000 * (d['now'] - d['t_capture']):.0f}; "
                  f"fiducials={d['n']}; fre_mm={fre}; needle={'sent' if tip_sent else 'not sent'}; "
                  f"validation={d['validation']}; alerts={','.join(d['alerts']) or 'none'}; "
                  f"coordinates={self.coordinates}")
        self._send(pyigtl.StringMessage(status, timestamp=ts, device_name="Status"))
        if (self._static_sent_at is None or d["now"] - self._static_sent_at >= STATIC_EVERY_S
                or plan.revision != self._static_revision):
            self._send_static(plan, ts)
            self._static_sent_at, self._static_revision = d["now"], plan.revision

    def _send_static(self, plan, ts: float) -> None:
        import pyigtl

        fids = plan.usable_fiducials()
        if fids:
            P = np.array([f.centre_lps_mm for f in fids], float)
            self._send(pyigtl.PointMessage(self._points(P), names=[f"F{f.id}" for f in fids],
                                           diameters=[2 * f.radius_mm for f in fids], timestamp=ts,
                                           device_name="Fiducials"))
        if plan.path_complete:
            self._send(pyigtl.PointMessage(self._points(np.array([plan.entry_lps_mm, plan.target_lps_mm])),
                                           names=["Entry", "Target"], timestamp=ts, device_name="Path"))

    def _points(self, P: np.ndarray) -> np.ndarray:
        return P @ self.F[:3, :3].T
