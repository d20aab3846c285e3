"""``monotracker serve``: the web app for the operating room.

    monotracker serve [--host 127.0.0.1] [--port 8080] [--allow-remote] [--sample]
        [--camera sim|device:N|file:PATH|folder:PATH|replay:DIR] [--calibration FILE]
        [--robot sim|ur:IP] [--pin PIN] [--trajectory still|drift|breathing|jumps] [--home DIR]
        [--record DIR] [--igtl-port PORT] [--password-file FILE] [--login-hours H]

Serves on 127.0.0.1 unless ``--allow-remote`` is given (any other ``--host`` is refused
without it: the page can move a robot). With ``--allow-remote`` the page needs a login first
(``ui/remote_login.py``): the session password is the first line of ``--password-file``, else
``$MONOTRACKER_PASSWORD``, else a random one printed here, on the console, only; a login lasts
``--login-hours`` (12). On 127.0.0.1 (the default) there is no login: whoever can use this
machine can use the page. Arming needs the operator PIN: ``--pin`` or
``$MONOTRACKER_PIN``; without either a random 6-digit PIN is made and printed here, on the
console, only. ``--sample`` loads the bundled sample CT at start (its fiducials still need the
operator's confirmation). Restarting restores the saved plan from the session folder (``--home``
or ``$MONOTRACKER_HOME``) and always starts disarmed.
"""

from __future__ import annotations

import argparse
import os
import secrets
import signal
import socket
import time

from monotracker.cli_args import existing_file, finite_float, home_folder, int_range
from monotracker.engine.config import TRAJECTORIES
from monotracker.engine.rigs.sources import GRAMMAR as CAMERA_GRAMMAR
from monotracker.errors import InputError
from monotracker.robot.backends import robot_spec

LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


def register(subparsers) -> None:
    p = subparsers.add_parser("serve", help="the web app (viser): CT, plan, register, robot",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int_range(1, 65535), default=8080, help="port (default 8080)")
    p.add_argument("--allow-remote", action="store_true",
                   help="allow a --host other than this machine (the page can move the robot); the page "
                        "then needs a login with the session password")
    p.add_argument("--password-file", default=None, metavar="FILE",
                   help="--allow-remote: the login password is this file's first line (default "
                        "$MONOTRACKER_PASSWORD, else a random one printed on this console)")
    p.add_argument("--login-hours", type=finite_float(0.001, 72.0), default=12.0, metavar="H",
                   help="--allow-remote: how long one login lasts (hours, default 12)")
    p.add_argument("--sample", action="store_true", help="load the bundled sample CT at start")
    p.add_argument("--camera", default="sim", help=f"{CAMERA_GRAMMAR} (default sim)")
    p.add_argument("--calibration", type=existing_file, default=None,
                   help="camera calibration file (OpenCV YAML/JSON) for a real camera; checked at start")
    p.add_argument("--robot", type=robot_spec, default="sim", help="sim | ur:IP (default sim; an IP address, no host names)")
    p.add_argument("--pin", default=None, help="operator PIN for arming (default $MONOTRACKER_PIN, else a random one)")
    p.add_argument("--tre-confidence", type=finite_float(0.0, 0.999), default=0.0, metavar="P",
                   help="trust a pose only when its error at the target stays within the 1 mm limit with "
                        "probability P by its predicted distribution (e.g. 0.95; default 0: the limit on the "
                        "predicted RMS error, and at most 0.1 %% over 2 mm)")
    p.add_argument("--ball-finish", default="read", metavar="FINISH",
                   help="the kit's balls: read (default: each frame's highlight decides), matte (only for a kit "
                        "known to be matte), or glossy "
                        "(glossy balls beside their contact shadows get a wider error cover with 6 or fewer in "
                        "view; say glossy for a far camera, and the layout planner predicts with it); a plan's own "
                        "finish (the CT step's 'Ball finish') wins")
    p.add_argument("--average-still-frames", type=int, default=0, metavar="N",
                   help="a dim, noisy camera: the detector reads the mean of up to N frames while the view "
                        "is still and the camera's noise is at least 1.8 grey levels (e.g. 8; restarted at any "
                        "motion or change; default 0 = off; costs 1-2.5 ms a frame)")
    p.add_argument("--trajectory", choices=TRAJECTORIES, default="breathing", help="simulated head motion (sim camera only)")
    p.add_argument("--home", type=home_folder, default=None, help="session folder, locked while the server runs (default $MONOTRACKER_HOME, else your ~/.monotracker)")
    p.add_argument("--record", type=home_folder, default=None, metavar="DIR",
                   help="record frames, detections, poses, robot and alerts into DIR (`monotracker replay DIR`)")
    p.add_argument("--igtl-port", type=int_range(1, 65535), default=None, metavar="PORT",
                   help="stream pose, needle, fiducials, path and status over OpenIGTLink (3D Slicer) on PORT "
                        "(127.0.0.1 unless --igtl-allow-remote)")
    p.add_argument("--igtl-allow-remote", action="store_true",
                   help="serve OpenIGTLink on every interface: it has no login, so anyone who reaches the port "
                        "receives the patient's registration and plan (--allow-remote does not imply it)")
    p.set_defaults(func=_serve)


def check_host(host: str, allow_remote: bool) -> None:
    if host not in LOCAL_HOSTS and not allow_remote:
        raise InputError(f"--host {host} would expose the robot's web page to the network; "
                         "add --allow-remote if that is intended")


def check_port_free(host: str, port: int) -> None:
    if not (0 < port < 65536):
        raise InputError(f"--port must be between 1 and 65535, not {port}")
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            raise InputError(f"cannot listen on {host}:{port}: {exc.strerror or exc}; choose another --port") from None


def resolve_pin(pin: str | None) -> tuple[str, bool]:
    """(PIN, generated?)."""
    pin = pin if pin is not None else os.environ.get("MONOTRACKER_PIN")
    if pin is None:
        return f"{secrets.randbelow(10**6):06d}", True
    pin = str(pin).strip()
    if len(pin) < 4 or not pin.isdigit():
        raise InputError("--pin must be at least 4 digits")
    return pin, False


def resolve_password(password_file: str | None) -> tuple[str, bool]:
    """The page-login password for ``--allow-remote``: (password, generated?). From
    ``--password-file`` (first line), else ``$MONOTRACKER_PASSWORD``, else a random one.
    InputError with one line for a bad file or a too short password."""
    from monotracker.ui.remote_login import check_password, read_password_file

    if password_file is not None:
        return read_password_file(password_file), False
    env = os.environ.get("MONOTRACKER_PASSWORD")
    if env is not None:
        return check_password(env.strip(), "MONOTRACKER_PASSWORD"), False
    return secrets.token_urlsafe(9), True


class StopSignals:
    """SIGINT/SIGTERM as a flag: create it before starting anything, :meth:`wait` in the main thread.

    The handler only appends the signal number to a list (no lock, no I/O, nothing that can block
    or deadlock when a signal arrives inside another handler or while the main thread holds a
    lock); the main thread polls the list and then does the shutdown. The handlers stay in place
    afterwards, so a repeated signal during the shutdown is recorded and ignored rather than
    interrupting it half way (every step of the shutdown has its own time limit). A signal that
    arrives while the app is still starting is kept: :meth:`wait` then returns at once."""

    def __init__(self):
        self.got: list[int] = []
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                signal.signal(sig, self._handler)
            except ValueError:  # not the main thread (tests)
                pass

    def _handler(self, signum, _frame) -> None:
        self.got.append(signum)

    def wait(self, poll_s: float = 0.2, stop=None) -> int:
        """Block until a signal was received (or ``stop()`` returns True); the first signal number (0: none)."""
        while not self.got and not (stop is not None and stop()):
            time.sleep(poll_s)
        return self.got[0] if self.got else 0


def restored_plan_line(session) -> str | None:
    """One plain line for the console when the session folder held an earlier plan, which the
    session restored (robot disarmed); None for a fresh folder."""
    from pathlib import Path

    snap = session.snapshot()
    if not (snap.fiducials or snap.plan.entry_lps_mm is not None or snap.plan.target_lps_mm is not None):
        return None
    path = Path(snap.plan_path)
    try:
        when = time.strftime("%Y-%m-%d %H:%M", time.localtime(path.stat().st_mtime))
    except OSError:
        when = "unknown"
    what = (f"{len(snap.fiducials)} fiducials {'locked' if snap.fiducials_locked else 'not locked yet'}, "
            f"{'entry and target set' if snap.plan.complete else 'no complete path'}")
    return (f"Restored the earlier plan in {path} (saved {when}: {what}); the robot starts DISARMED. "
            "To start afresh: 'New plan' on the page, or another folder with --home DIR.")


def _serve(args) -> int:
    from monotracker.engine import Session, SessionConfig

    check_host(args.host, args.allow_remote)
    check_port_free(args.host, args.port)
    pin, generated = resolve_pin(args.pin)
    password = None
    if args.allow_remote:
        password, password_generated = resolve_password(args.password_file)
    elif args.password_file is not None:
        raise InputError("--password-file is for --allow-remote (on this machine only the page has no login)")
    if args.igtl_allow_remote and args.igtl_port is None:
        raise InputError("--igtl-allow-remote needs --igtl-port PORT")
    cfg = SessionConfig(home=args.home, camera=args.camera, robot=args.robot, arm_pin=pin,
                        trajectory=args.trajectory, clock="real", tre_confidence=args.tre_confidence,
                        ball_finish=args.ball_finish, average_still_frames=args.average_still_frames)
    cfg.validate()
    signals = StopSignals()  # from here on a stop signal is a flag the main thread acts on
    if args.calibration is not None:  # a bad file is refused now, not when the camera starts
        from monotracker.vision.camera_model import CameraModel

        CameraModel.load(args.calibration)  # InputError with the reason
    session = Session(cfg)  # refused with one line while another session holds the folder
    app = streamer = None
    try:
        print(f"session folder: {session.home} (locked while this server runs)", flush=True)
        restored = restored_plan_line(session)
        if restored:
            print(restored, flush=True)
        if args.calibration is not None:
            r = session.set_camera(args.camera, str(args.calibration))
            if not r.ok:
                raise InputError(r.message)
        if args.record is not None:
            r = session.start_recording(args.record)
            if not r.ok:
                raise InputError(f"--record: {r.message}")
        session.start()
        if args.igtl_port is not None:
            from monotracker.interop.igtl import IGTLStreamer

            streamer = IGTLStreamer(session, args.igtl_port, args.igtl_allow_remote).start()
            print(f"OpenIGTLink: {streamer.host}:{streamer.port} (CTToCamera, NeedleTipToCT, Status, "
                  "Fiducials, Path)", flush=True)
        if args.sample:
            snap = session.snapshot()
            if not snap.fiducials_locked:
                session.load_sample_ct()
        from monotracker.ui.app import MonoTrackerApp

        login = None
        if password is not None:
            from monotracker.ui.remote_login import for_session

            login = for_session(session, password, ttl_s=3600.0 * args.login_hours)
        app = MonoTrackerApp(session, args.host, args.port, login=login)
        app.start()
        print(f"MonoTracker is running: open {app.url} in a browser (Ctrl-C to stop)", flush=True)
        if login is not None:
            print(f"the page needs a login (session password, valid {args.login_hours:g} h per login)", flush=True)
            if password_generated:
                print(f"session password for the page: {password}  (set your own with --password-file or "
                      "MONOTRACKER_PASSWORD)", flush=True)
        if generated:
            print(f"operator PIN for arming: {pin}  (set your own with --pin or MONOTRACKER_PIN)", flush=True)
        signals.wait()
        print("stopping: robot disarmed, threads stopped", flush=True)
        return 0
    finally:
        if app is not None:
            app.stop()
        if streamer is not None:
            streamer.stop()
        session.shutdown()
