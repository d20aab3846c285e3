"""The page login for ``monotracker serve --allow-remote``: nothing of the app passes before it.

With ``--allow-remote`` viser listens on 127.0.0.1 only (an ephemeral port) and this module's
:class:`LoginProxy` listens on the public address. The proxy answers every request itself until
the browser holds a valid session cookie; then it relays HTTP and the websocket to viser as is.
So an unauthenticated client gets the login page, a redirect to it, or ``401`` - never viser's
page, its websocket, nor any scene/GUI message (CT, camera image, controls).

* :class:`LoginGate` (no network, no threads): the session password behind the shared
  :class:`~monotracker.engine.access.PinGuard` (5 wrong tries, then a 30 s lockout that doubles
  while wrong tries go on; while locked even the right password is refused; one guard for every
  address, so many addresses do not multiply the tries), and the sessions:
  a random 256-bit id per login, kept server side with an absolute expiry (``ttl_s``), revoked
  by logout. The cookie carries only that id (``HttpOnly``, ``SameSite=Strict``, ``Path=/``,
  ``Max-Age``); an id the server does not hold (forged, expired, logged out) is worth nothing,
  which a stateless signed cookie could not promise at logout.
* :class:`LoginProxy`: the aiohttp server (its own thread and event loop). ``GET /login`` the
  form, ``POST /login`` one try, ``GET /logout`` ends the session. A websocket upgrade without a
  valid cookie, or from a page of another origin, is refused before it reaches viser. Every
  second it closes the websockets whose session expired or was logged out, and keeps the
  ``login_lockout`` alarm in step with the guard.

Audit (the session's log): ``login_ok``, ``login_refused`` (one row per wrong try, never the
password), ``logout``, ``login_expired``; the ``login_lockout`` alarm while locked (one alert when
a lockout begins). Times are ``time.monotonic()`` seconds.

Not covered here: the traffic is plain HTTP (no TLS); on a network that is not closed to
outsiders, put a TLS reverse proxy in front. Local users of this machine can reach viser's
loopback port directly, as with the loopback default (which needs no login).
"""

from __future__ import annotations

import asyncio
import html
import logging
import secrets
import threading
import time
from dataclasses import dataclass

from monotracker.engine.access import PinGuard
from monotracker.engine.snapshot import CommandResult
from monotracker.errors import InputError

log = logging.getLogger(__name__)

COOKIE = "mt_session"
#: minimum length of a session password from a file or the environment
MIN_PASSWORD_LEN = 8
#: headers not relayed between the browser and viser (hop-by-hop, or set by the proxy itself)
HOP_HEADERS = frozenset(h.lower() for h in (
    "Connection", "Keep-Alive", "Proxy-Authenticate", "Proxy-Authorization", "TE", "Trailers",
    "Transfer-Encoding", "Upgrade", "Content-Length", "Host", "Cookie", "Set-Cookie"))


def check_password(password: str, where: str) -> str:
    """The password, or InputError with one line when it is too short / has control characters."""
    if len(password) < MIN_PASSWORD_LEN:
        raise InputError(f"{where}: the login password must be at least {MIN_PASSWORD_LEN} characters")
    if any(ord(c) < 32 for c in password):
        raise InputError(f"{where}: the login password must be one line of printable characters")
    return password


def read_password_file(path) -> str:
    """The first line of ``path`` (stripped) as the login password; InputError with one line
    when the file is missing, unreadable, not text, empty or too short."""
    try:
        raw = open(path, "rb").read(4096)
    except FileNotFoundError:
        raise InputError(f"--password-file {path}: file not found") from None
    except IsADirectoryError:
        raise InputError(f"--password-file {path}: is a folder, not a file") from None
    except OSError as exc:
        raise InputError(f"--password-file {path}: cannot read it ({exc.strerror or exc})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(f"--password-file {path}: not a UTF-8 text file") from None
    lines = text.splitlines()
    password = lines[0].strip() if lines else ""
    if not password:
        raise InputError(f"--password-file {path}: the first line is empty (write the password there)")
    return check_password(password, f"--password-file {path}")


@dataclass
class _Login:
    expires: float  # time.monotonic() s
    peer: str


class LoginGate:
    """The session password and the logged-in sessions (thread-safe; see the module docstring).

    ``password``: the session password. ``ttl_s``: how long one login lasts (s, absolute).
    ``max_tries`` / ``lockout_s``: the wrong-try limit (see :class:`PinGuard`). ``clock``: seconds
    (``time.monotonic``). ``audit(code, message, level)``: one audit row (never the password);
    ``lockout(locked_s, message)``: the lockout alarm (``locked_s`` 0 clears it)."""

    def __init__(self, password: str, *, ttl_s: float = 12 * 3600.0, max_tries: int = 5, lockout_s: float = 30.0,
                 clock=time.monotonic, audit=None, lockout=None):
        # one wrong-try guard for the whole page, whatever address the tries come from: per address,
        # an attacker with many addresses (or one that rotates them) multiplies the tries (issue 36:
        # 33 guesses from several addresses, then in). The price: a flood of wrong tries also locks
        # out new logins from the staff (not the logged-in stations, whose sessions stay valid),
        # which the login_lockout alarm makes visible on every station.
        self._guard = PinGuard(password, max_tries=max_tries, lockout_s=lockout_s, noun="password")
        self._last_wrong_peer = ""
        self.max_tries = int(max_tries)
        self.ttl_s = float(ttl_s)
        self._clock = clock
        self._audit = audit or (lambda code, message, level: None)
        self._lockout = lockout or (lambda locked_s, message: None)
        self._lock = threading.Lock()
        self._logins: dict[str, _Login] = {}
        self._alarm_on = False

    def try_login(self, password: str, peer: str = "") -> tuple[CommandResult, str | None]:
        """One try: ``(ok result, session id)`` or ``(refusal with one line, None)``."""
        now = self._clock()
        guard = self._guard
        was_locked = guard.locked_for(now) > 0
        r = guard.check(str(password or ""), now)
        if not r.ok:
            self._last_wrong_peer = str(peer)
            self._audit("login_refused", f"page login refused from {peer or 'unknown'}: {r.message}", "warning")
            locked = guard.locked_for(now)
            if locked > 0 and not was_locked:
                log.warning("page login locked for %.0f s after wrong passwords (last from %s)", locked, peer)
            self.sync_alarm()
            return r, None
        token = secrets.token_urlsafe(32)
        with self._lock:
            self._logins[token] = _Login(now + self.ttl_s, str(peer))
        self._audit("login_ok", f"page login from {peer or 'unknown'} (valid {self.ttl_s / 3600:.1f} h)", "info")
        return CommandResult(True, "logged in"), token

    def valid(self, token: str | None) -> bool:
        """True while ``token`` is a live session (held here, not expired, not logged out)."""
        if not token:
            return False
        with self._lock:
            lg = self._logins.get(str(token))
            return lg is not None and self._clock() < lg.expires

    def logout(self, token: str | None) -> bool:
        """End the session ``token``; True if it was live."""
        with self._lock:
            lg = self._logins.pop(str(token or ""), None)
        if lg is None:
            return False
        self._audit("logout", f"page logout ({lg.peer or 'unknown'})", "info")
        return True

    def expire(self) -> list[str]:
        """Drop the sessions past their expiry; their ids (their websockets must close)."""
        now = self._clock()
        with self._lock:
            gone = [t for t, lg in self._logins.items() if now >= lg.expires]
            peers = [self._logins.pop(t).peer for t in gone]
        for p in peers:
            self._audit("login_expired", f"page login of {p or 'unknown'} expired after {self.ttl_s / 3600:.2f} h", "info")
        return gone

    def locked_for(self, peer: str | None = None) -> float:
        """Seconds the page login stays locked (one lockout for every address; ``peer`` is
        accepted for callers that name one and changes nothing)."""
        return self._guard.locked_for(self._clock())

    def sync_alarm(self) -> None:
        """Keep the ``login_lockout`` alarm on while locked, off after."""
        left = self.locked_for()
        if left > 0:
            self._alarm_on = True
            last = f" (the last from {self._last_wrong_peer})" if self._last_wrong_peer else ""
            self._lockout(left, f"page login locked for {left:.0f} s after {self.max_tries} wrong passwords{last}: "
                          "new logins from every address are refused meanwhile")
        elif self._alarm_on:
            self._alarm_on = False
            self._lockout(0.0, "")


def for_session(session, password: str, ttl_s: float = 12 * 3600.0, **kw) -> LoginGate:
    """A :class:`LoginGate` whose audit rows and lockout alarm go to ``session`` (an engine
    Session); ``kw``: the other :class:`LoginGate` arguments (``max_tries``, ``lockout_s``)."""
    return LoginGate(password, ttl_s=ttl_s,
                     audit=lambda code, message, level: session.record(code, message, level=level),
                     lockout=session.report_login_lockout, **kw)


LOGIN_PAGE = """<!doctype html><html><head><meta charset="utf-8"><title>MonoTracker - log in</title>
<meta name="viewport" content="width=device-width,initial-scale=1">
<style>body{{font-family:system-ui,sans-serif;background:#f2f4f7;display:flex;justify-content:center;margin-top:12vh}}
form{{background:#fff;padding:28px 32px;border-radius:8px;box-shadow:0 2px 10px #0002;width:340px}}
h1{{font-size:20px;margin:0 0 6px}} p{{color:#444;font-size:14px}} input{{width:100%;font-size:18px;padding:8px;box-sizing:border-box}}
button{{margin-top:14px;width:100%;font-size:18px;padding:10px;background:#2b6cb0;color:#fff;border:0;border-radius:6px}}
#mt-login-error{{color:#c81e1e;font-weight:600}}</style></head><body>
<form method="post" action="/login"><h1>MonoTracker</h1>
<p>This station serves the operating-room web app to the network. Enter the session password
(printed on the server's console, or set with --password-file / MONOTRACKER_PASSWORD).</p>
<p id="mt-login-error">{error}</p>
<label for="mt-password">Session password</label>
<input id="mt-password" name="password" type="password" autocomplete="current-password" autofocus required>
<button id="mt-login" type="submit">Log in</button></form></body></html>"""


class LoginProxy:
    """The login in front of viser (see the module docstring). ``gate``: a :class:`LoginGate`;
    ``host``/``port``: the public address; ``upstream_port``: viser's port on 127.0.0.1."""

    def __init__(self, gate: LoginGate, host: str, port: int, upstream_port: int, *, sweep_s: float = 1.0):
        self.gate = gate
        self.host, self.port = host, int(port)
        self.upstream = f"127.0.0.1:{int(upstream_port)}"
        self.sweep_s = float(sweep_s)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._stop: asyncio.Event | None = None
        self._sockets: dict[str, set] = {}  # session id -> open browser websockets
        self.stats = {"ws_refused": 0, "http_refused": 0, "ws_open": 0}

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "LoginProxy":
        """Listen; raises InputError with one line when the address cannot be used."""
        self._thread = threading.Thread(target=self._run, name="monotracker-login-proxy", daemon=True)
        self._thread.start()
        if not self._ready.wait(60.0):
            raise InputError(f"the login proxy did not start on {self.host}:{self.port} within 60 s")
        if self._error is not None:
            err = self._error
            if isinstance(err, OSError):
                raise InputError(f"cannot listen on {self.host}:{self.port}: {err.strerror or err}; "
                                 "choose another --port") from None
            raise InputError(f"the login proxy failed to start: {type(err).__name__}: {err}") from None
        return self

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            try:
                self._loop.call_soon_threadsafe(self._stop.set)
            except RuntimeError:
                pass
        if self._thread is not None:
            self._thread.join(timeout=10.0)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._main())
        except BaseException as exc:  # reported to start() or logged
            if not self._ready.is_set():
                self._error = exc
                self._ready.set()
            else:
                log.exception("login proxy stopped")
        finally:
            loop.close()

    async def _main(self) -> None:
        from aiohttp import ClientSession, ClientTimeout, TCPConnector, web

        self._stop = asyncio.Event()
        app = web.Application(client_max_size=64 * 1024)
        app.router.add_route("GET", "/login", self._login_form)
        app.router.add_route("POST", "/login", self._login_post)
        app.router.add_route("GET", "/logout", self._logout)
        app.router.add_route("*", "/{tail:.*}", self._relay)
        self._client = ClientSession(connector=TCPConnector(limit=0), auto_decompress=False,
                                     timeout=ClientTimeout(total=None, sock_connect=10))
        runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await runner.setup()
        try:
            site = web.TCPSite(runner, self.host, self.port, reuse_address=True)
            await site.start()
            self._ready.set()
            sweeper = asyncio.ensure_future(self._sweep())
            await self._stop.wait()
            sweeper.cancel()
            for socks in list(self._sockets.values()):
                for ws in list(socks):
                    await ws.close(code=1001, message=b"server stopping")
        finally:
            await self._client.close()
            await runner.cleanup()

    async def _sweep(self) -> None:
        """Close the websockets of sessions that expired or were logged out; the lockout alarm."""
        while True:
            await asyncio.sleep(self.sweep_s)
            try:
                self.gate.expire()
                self.gate.sync_alarm()
                for token in [t for t in self._sockets if not self.gate.valid(t)]:
                    await self._close_session_sockets(token, "session ended: log in again")
            except Exception:  # the sweep must go on
                log.exception("login sweep failed")

    async def _close_session_sockets(self, token: str, why: str) -> None:
        for ws in list(self._sockets.pop(token, ())):
            await ws.close(code=4401, message=why.encode())

    # ------------------------------------------------------------------ handlers
    def _token(self, request) -> str | None:
        return request.cookies.get(COOKIE)

    @staticmethod
    def _secure_headers(resp):
        resp.headers["Cache-Control"] = "no-store"
        resp.headers["X-Frame-Options"] = "DENY"
        resp.headers["Referrer-Policy"] = "no-referrer"
        resp.headers["X-Content-Type-Options"] = "nosniff"
        return resp

    def _page(self, error: str = "", status: int = 200):
        from aiohttp import web

        return self._secure_headers(web.Response(text=LOGIN_PAGE.format(error=html.escape(error)), status=status,
                                                 content_type="text/html"))

    async def _login_form(self, request):
        from aiohttp import web

        if self.gate.valid(self._token(request)):
            raise web.HTTPSeeOther("/")
        return self._page()

    async def _login_post(self, request):
        from aiohttp import web

        try:
            form = await request.post()
        except Exception:  # noqa: BLE001 - an oversized or malformed form
            return self._page("the form could not be read; try again", status=400)
        r, token = self.gate.try_login(str(form.get("password", "")), request.remote or "")
        if token is None:
            return self._page(r.message, status=401)
        resp = web.HTTPSeeOther("/")
        resp.set_cookie(COOKIE, token, max_age=int(self.gate.ttl_s), httponly=True, samesite="Strict", path="/")
        self._secure_headers(resp)
        raise resp

    async def _logout(self, request):
        from aiohttp import web

        token = self._token(request)
        self.gate.logout(token)
        if token:
            await self._close_session_sockets(token, "logged out")
        resp = web.HTTPSeeOther("/login")
        resp.set_cookie(COOKIE, "", max_age=0, httponly=True, samesite="Strict", path="/")
        self._secure_headers(resp)
        raise resp

    def _same_origin(self, request) -> bool:
        origin = request.headers.get("Origin")
        if origin is None:
            return True  # not a browser page (a browser always sends Origin on a websocket)
        from yarl import URL

        try:
            o = URL(origin)
        except ValueError:
            return False
        host = request.headers.get("Host", "")
        return f"{o.host}:{o.port}" == host or (o.host == host and o.port in (80, 443))

    async def _relay(self, request):
        from aiohttp import web

        token = self._token(request)
        is_ws = request.headers.get("Upgrade", "").lower() == "websocket"
        if not self.gate.valid(token):
            if is_ws:
                self.stats["ws_refused"] += 1
                return self._secure_headers(web.Response(status=401, text="login required"))
            self.stats["http_refused"] += 1
            if request.method in ("GET", "HEAD") and request.path in ("/", "/index.html"):
                raise self._secure_headers(web.HTTPSeeOther("/login"))
            return self._secure_headers(web.Response(status=401, text="login required"))
        if is_ws:
            if not self._same_origin(request):
                self.stats["ws_refused"] += 1
                return self._secure_headers(web.Response(status=403, text="websocket from another origin"))
            return await self._relay_ws(request, token)
        return await self._relay_http(request)

    async def _relay_http(self, request):
        from aiohttp import ClientError, web

        headers = {k: v for k, v in request.headers.items() if k.lower() not in HOP_HEADERS}
        body = await request.read() if request.can_read_body else None
        try:
            async with self._client.request(request.method, f"http://{self.upstream}{request.path_qs}",
                                            headers=headers, data=body, allow_redirects=False) as up:
                payload = await up.read()
                out = web.Response(status=up.status, body=payload)
                for k, v in up.headers.items():
                    if k.lower() not in HOP_HEADERS:
                        out.headers[k] = v
        except ClientError as exc:
            return web.Response(status=502, text=f"the web app is not answering ({type(exc).__name__})")
        out.headers.setdefault("X-Frame-Options", "DENY")
        return out

    async def _relay_ws(self, request, token: str):
        from aiohttp import ClientError, WSMsgType, web

        protocols = [p.strip() for p in request.headers.get("Sec-WebSocket-Protocol", "").split(",") if p.strip()]
        try:
            up = await self._client.ws_connect(f"http://{self.upstream}{request.path_qs}", protocols=protocols,
                                               max_msg_size=0, compress=0, autoping=True)
        except (ClientError, OSError) as exc:
            return web.Response(status=502, text=f"the web app is not answering ({type(exc).__name__})")
        ws = web.WebSocketResponse(protocols=[up.protocol] if up.protocol else (), max_msg_size=0,
                                   compress=False, autoping=True, heartbeat=30.0)
        await ws.prepare(request)
        self._sockets.setdefault(token, set()).add(ws)
        self.stats["ws_open"] += 1

        async def pump(src, dst):
            try:
                async for msg in src:
                    if msg.type == WSMsgType.BINARY:
                        await dst.send_bytes(msg.data)
                    elif msg.type == WSMsgType.TEXT:
                        await dst.send_str(msg.data)
                    else:
                        break
            except (ClientError, ConnectionError, RuntimeError):  # the other side went away
                pass

        tasks = [asyncio.ensure_future(pump(ws, up)), asyncio.ensure_future(pump(up, ws))]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in tasks:
                t.cancel()
            await up.close()
            if not ws.closed:
                await ws.close()
            socks = self._sockets.get(token)
            if socks is not None:
                socks.discard(ws)
                if not socks:
                    self._sockets.pop(token, None)
            self.stats["ws_open"] -= 1
        return ws
